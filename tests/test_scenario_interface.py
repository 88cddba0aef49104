"""The Scenario contract (``ttompc.scenarios.base``), checked for every built-in scenario: sampling, shapes, the
torch model against the exact step, the convex model against the step, reference-independent constraint structure,
violation counts, representation and feature round trips, validation, and REL→SCP solutions."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ttompc.scenarios import (
    InfeasibleProblemError,
    Problem,
    Scenario,
    Window,
    freeflyer,
    get_scenario,
    list_scenarios,
    quadrotor,
)
from ttompc.solvers.scp import solve_problem

BUILTIN = [n for n in list_scenarios() if type(get_scenario(n)).__module__.startswith("ttompc.scenarios.")]
# A model-representation state inside a keep-out zone at step 0 (RPOD: RTN position 17 m from the ISS).
INSIDE_KEEPOUT = {
    "freeflyer": np.concatenate([freeflyer.OBSTACLES[0], np.zeros(4)]),
    "quadrotor": np.concatenate([quadrotor.OBSTACLES[0], np.zeros(3)]),
    "rpod": np.array([10.0, 10.0, 10.0, 0.0, 0.0, 0.0]),
}
WINDOWS = [(0, 100), (37, 20), (85, 10), (95, 5)]


@pytest.fixture(params=BUILTIN)
def sc(request: pytest.FixtureRequest) -> Scenario:
    return get_scenario(request.param)


def _problems(sc: Scenario, n: int, seed: int = 0) -> list[Problem]:
    rng = np.random.default_rng(seed)
    return [sc.sample(rng) for _ in range(n)]


def _random_controls(sc: Scenario, problem: Problem, rng: np.random.Generator, H: int | None = None) -> np.ndarray:
    """Controls of a plausible size: impulses ~1e-3 m/s (free-flyer, RPOD), forces ~1 N (quadrotor)."""
    H = problem.n_steps if H is None else H
    scale = 1.0 if sc.cost_norm == "quad" else 1e-3
    return rng.normal(scale=scale, size=(H, sc.control_dim))


def _structure(blocks: list) -> list[tuple]:
    return [
        (
            b.name,
            b.kind,
            b.steps.tolist(),
            b.Gx.shape,
            None if b.Gu is None else b.Gu.shape,
            b.h.shape,
            b.nonconvex,
            b.obstacle,
            b.soft,
            b.weight,
        )
        for b in blocks
    ]


def test_sample_is_deterministic(sc: Scenario) -> None:
    a, b = _problems(sc, 3, seed=5), _problems(sc, 3, seed=5)
    c = _problems(sc, 3, seed=6)
    for p, q in zip(a, b, strict=True):
        np.testing.assert_array_equal(p.x0, q.x0)
        np.testing.assert_array_equal(p.goal, q.goal)
        assert p.dt == q.dt
        for key, value in sc.problem_features(p).items():
            np.testing.assert_array_equal(value, sc.problem_features(q)[key])
    assert not np.array_equal(a[0].x0, c[0].x0)


def test_problem_shapes_and_validation(sc: Scenario) -> None:
    for p in _problems(sc, 30):
        assert p.x0.shape == p.goal.shape == (sc.state_dim,)
        assert p.n_steps == sc.n_steps and p.dt > 0
        sc.validate(p)
        assert sc.violations(p, p.x0[None]).tolist() == [0]
    assert len(sc.state_labels) == sc.state_dim and len(sc.control_labels) == sc.control_dim
    assert len(sc.mpc.dist) == sc.state_dim


def test_batched_model_matches_step(sc: Scenario) -> None:
    problems = _problems(sc, 3, seed=1)
    model = sc.batched_model(problems)
    rng = np.random.default_rng(2)
    for k in (0, 37, 89, 90, sc.n_steps - 1):
        X = np.stack([sc.initial_guess(p)[0][k] for p in problems])
        X = X + rng.normal(scale=0.1, size=X.shape) * (1 + np.abs(X))
        U = np.stack([_random_controls(sc, p, rng, 1)[0] for p in problems])
        S = np.stack([sc.to_model_states(p, x[None], start=k)[0] for p, x in zip(problems, X, strict=True)])
        expected = np.stack(
            [
                sc.to_model_states(p, sc.step(p, k, x, u)[None], start=k + 1)[0]
                for p, x, u in zip(problems, X, U, strict=True)
            ]
        )
        got = model.step(torch.as_tensor(S), torch.as_tensor(U), k).numpy()
        np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-10 * np.abs(expected).max())
        got32 = model.step(torch.as_tensor(S, dtype=torch.float32), torch.as_tensor(U, dtype=torch.float32), k)
        assert got32.dtype == torch.float32
        np.testing.assert_allclose(got32.numpy(), expected, rtol=1e-4, atol=1e-5 * np.abs(expected).max())
        S_bad = S.copy()
        S_bad[0] = INSIDE_KEEPOUT.get(sc.name, S[0])
        counts = model.violations(torch.as_tensor(S_bad), k).numpy()
        ref = [
            sc.violations(p, sc.from_model_states(p, s[None], start=k), start=k)[0]
            for p, s in zip(problems, S_bad, strict=True)
        ]
        np.testing.assert_array_equal(counts, ref)


@pytest.mark.parametrize("start,length", WINDOWS[:2])
def test_convex_model_reproduces_the_step(sc: Scenario, start: int, length: int) -> None:
    """At a dynamically consistent reference the affine model is the exact step; around it the error is zero for
    exactly linear dynamics and O(δ²) otherwise."""
    problem = _problems(sc, 1, seed=3)[0]
    rng = np.random.default_rng(4)
    U_all = _random_controls(sc, problem, rng)
    X_all = sc.rollout(problem, U_all)
    w = Window(start, length, problem.n_steps)
    X, U = X_all[start : w.stop + 1], U_all[start : w.stop]
    m = sc.convex_model(problem, w, X, U)
    assert m.A.shape == (length, sc.state_dim, sc.state_dim) and m.B.shape == (length, sc.state_dim, sc.control_dim)
    assert m.c.shape == (length, sc.state_dim)
    scale = 1 + np.abs(X).max()

    def model_error(Xp: np.ndarray, Up: np.ndarray) -> float:
        pred = np.einsum("jab,jb->ja", m.A, Xp[:-1]) + np.einsum("jab,jb->ja", m.B, Up) + m.c
        exact = np.stack([sc.step(problem, start + j, Xp[j], Up[j]) for j in range(length)])
        return float(np.abs(pred - exact).max())

    assert model_error(X, U) <= 1e-12 * scale
    dX, dU = rng.normal(size=X.shape) * (1 + np.abs(X)), rng.normal(size=U.shape) * np.abs(U).max()
    errs = [model_error(X + d * dX, U + d * dU) for d in (1e-2, 5e-3)]
    if sc.exact_linear_dynamics:
        assert max(errs) <= 1e-12 * scale
    else:
        assert errs[0] / errs[1] == pytest.approx(4.0, rel=0.1)


@pytest.mark.parametrize("start,length", WINDOWS)
def test_constraint_structure_is_independent_of_the_reference(sc: Scenario, start: int, length: int) -> None:
    problem = _problems(sc, 1, seed=5)[0]
    w = Window(start, length, problem.n_steps)
    X1, U1 = sc.initial_guess(problem, w)
    rng = np.random.default_rng(6)
    U2 = _random_controls(sc, problem, rng, length)
    X2 = sc.rollout(problem, U2, start=start, x=X1[0] + rng.normal(size=sc.state_dim) * (1 + np.abs(X1[0])))
    for obstacles in (True, False):
        b1 = sc.constraints(problem, w, X1, U1, obstacles=obstacles)
        b2 = sc.constraints(problem, w, X2, U2, obstacles=obstacles)
        assert _structure(b1) == _structure(b2)
        for b in b1:
            assert b.steps.min() >= 0 and b.steps.max() <= length
            assert np.all(np.isfinite(b.Gx)) and np.all(np.isfinite(b.h))
            if b.obstacle:
                assert b.nonconvex and 0 not in b.steps.tolist()
            if b.Gu is not None:
                assert b.steps.max() < length
        if not obstacles:
            assert not any(b.obstacle for b in b1)


def test_violation_counts(sc: Scenario) -> None:
    if sc.name not in INSIDE_KEEPOUT:
        pytest.skip("no known keep-out state")
    problem = _problems(sc, 1, seed=7)[0]
    S = np.repeat(sc.to_model_states(problem, problem.x0[None]), 6, axis=0)
    S[3] = INSIDE_KEEPOUT[sc.name]
    counts = sc.violations(problem, sc.from_model_states(problem, S))
    assert counts.dtype.kind == "i" and counts.shape == (6,)
    assert counts[3] >= 1 and counts.sum() == counts[3]


def test_model_state_round_trip(sc: Scenario) -> None:
    problem = _problems(sc, 1, seed=8)[0]
    X = np.random.default_rng(9).normal(size=(problem.n_steps + 1, sc.state_dim)) * 10
    np.testing.assert_allclose(sc.from_model_states(problem, sc.to_model_states(problem, X)), X, atol=1e-8)
    part = X[37:47]
    np.testing.assert_allclose(sc.to_model_states(problem, part, start=37), sc.to_model_states(problem, X)[37:47])
    np.testing.assert_allclose(
        sc.model_goal(problem), sc.to_model_states(problem, problem.goal[None], start=problem.n_steps)[0], atol=1e-9
    )


def test_problem_features_round_trip(sc: Scenario) -> None:
    for p in _problems(sc, 3, seed=10):
        feats = {k: np.asarray(v, dtype=np.float64) for k, v in sc.problem_features(p).items()}  # as stored
        q = sc.problem_from_features(p.x0, p.goal, p.dt, feats)
        np.testing.assert_array_equal(q.x0, p.x0)
        np.testing.assert_allclose(q.goal, p.goal, atol=1e-12)
        assert q.dt == p.dt and q.n_steps == p.n_steps
        for key, value in sc.problem_features(q).items():
            np.testing.assert_array_equal(value, feats[key])
        u = np.full(sc.control_dim, 1e-3)
        np.testing.assert_array_equal(sc.step(q, 50, q.x0, u), sc.step(p, 50, p.x0, u))


def test_validate_rejects_a_start_inside_a_keepout(sc: Scenario) -> None:
    if sc.name not in INSIDE_KEEPOUT:
        pytest.skip("no known keep-out state")
    p = _problems(sc, 1, seed=11)[0]
    x0 = sc.from_model_states(p, INSIDE_KEEPOUT[sc.name][None])[0]
    bad = sc.problem_from_features(x0, p.goal, p.dt, sc.problem_features(p))
    with pytest.raises(InfeasibleProblemError):
        sc.validate(bad)


@pytest.mark.parametrize("seed", [0, 1])
def test_rel_then_scp(sc: Scenario, seed: int) -> None:
    problem = _problems(sc, 1, seed=100 + seed)[0]
    rel, scp = solve_problem(sc, problem, backend="clarabel")  # deterministic reference backend
    assert rel.success, rel.summary()
    assert scp is not None and scp.success, scp and scp.summary()
    assert rel.cost <= scp.cost * (1 + 1e-5) + 1e-6
    w = Window.full(problem)
    tol = sc.scp.feas_tol
    np.testing.assert_allclose(scp.X[0], problem.x0, atol=1e-9)
    np.testing.assert_allclose(scp.X[-1], problem.goal, atol=tol)
    assert sc.constraint_violation(problem, scp.X, scp.U, w) <= tol
    assert sc.path_violation(problem, scp.X, scp.U, w) <= tol
    assert sc.violations(problem, scp.X).sum() == 0


def test_plot_smoke(sc: Scenario) -> None:
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    problem = _problems(sc, 1, seed=12)[0]
    fig, ax = plt.subplots()
    sc.plot(ax, problem, {"guess": sc.initial_guess(problem)[0]})
    assert ax.lines
    plt.close(fig)
