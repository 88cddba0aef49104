"""The Riccati kernel's warm start (``RiccatiOptions.warm``, ``riccati_rows.warm_start``) and the backend's use of it
between a solve's SCP iterations (``RiccatiSolver.warm``): a centred start, the cold start's optima in fewer
interior-point iterations, whole solves at the cold start's costs and statuses, MPC windows cold."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from helpers import qp_subproblem

from ttompc.scenarios import Window, get_scenario
from ttompc.solvers import SCPProblem, TerminalCost, solve_problem, solve_scp
from ttompc.solvers.backends import riccati_kernel
from ttompc.solvers.backends.riccati import GAP_TOL, MAX_ITER, TOL, WARM, RiccatiSolver, StageQP, status_iterations
from ttompc.solvers.backends.riccati_qp import DualState, RiccatiOptions

S, LAM, E, MU = range(4)  # riccati_rows' columns


def _copy(x):
    """A deep copy of a stage QP (nested named tuples of arrays)."""
    return type(x)(*(_copy(f) for f in x)) if isinstance(x, tuple) else np.array(x, copy=True)


def _cold_subproblems(monkeypatch: pytest.MonkeyPatch, name: str, seed: int) -> list[list[dict]]:
    """Per SCP solve of REL + SCP on ``seed`` (cold starts), its subproblems in order: the QP, and the solve's
    solution, multipliers, final constraint state, status, iterations and objective."""
    from ttompc.solvers import scp as scp_module

    runs: list[list[dict]] = []
    solve, run_scp = riccati_kernel.solve, scp_module.run_scp

    def captured(qp, y, pi, options, state=None):
        copy, state = _copy(qp), DualState.empty(qp)
        out = solve(qp, y, pi, options, state)
        runs[-1].append(dict(qp=copy, y=y.copy(), pi=pi.copy(), state=state, out=out, objective=qp.objective(y)))
        return out

    def run(*args, **kwargs):
        runs.append([])
        return run_scp(*args, **kwargs)

    monkeypatch.setattr(RiccatiSolver, "warm", 0.0)
    monkeypatch.setattr(riccati_kernel, "solve", captured)
    monkeypatch.setattr(scp_module, "run_scp", run)
    sc = get_scenario(name)
    solve_problem(sc, sc.sample(np.random.default_rng(seed)))
    monkeypatch.undo()
    return [r for r in runs if len(r) > 1]


@pytest.mark.parametrize(("name", "seed"), [("freeflyer", 5), ("quadrotor", 1)])
def test_warm_start_reaches_the_cold_optimum_in_fewer_iterations(monkeypatch, name: str, seed: int) -> None:
    """Each later subproblem of an SCP solve, started from the previous one's solution, multipliers and constraint
    state: converged, at the cold start's objective (to the kernel's tolerances), in fewer iterations in all
    (measured: about half, docs/benchmarks.md)."""
    runs = _cold_subproblems(monkeypatch, name, seed)
    cold = warm = 0
    for run in runs:
        for prev, sub in itertools.pairwise(run):
            if prev["out"].status != 0:  # (the backend starts cold after those)
                continue
            y, pi = prev["y"].copy(), prev["pi"].copy()
            state = DualState(prev["state"].boxes.copy(), prev["state"].rows.copy())
            out = riccati_kernel.solve(sub["qp"], y, pi, RiccatiOptions(TOL, GAP_TOL, MAX_ITER, WARM), state)
            assert out.status == 0
            assert sub["qp"].objective(y) == pytest.approx(sub["objective"], rel=1e-7, abs=1e-9)
            cold, warm = cold + sub["out"].iterations, warm + out.iterations
    assert cold > 0 and warm <= 0.8 * cold, (warm, cold)


def test_warm_start_is_centred() -> None:
    """The start (no iteration: ``max_iter`` 0) from a state with zeros, negatives and tiny values: the slack s
    re-evaluated as d − gᵀy + e, then each pair (s, λ), (e, μ) only raised, to a product ≥ δ, its larger member kept
    where it is ≥ √δ and a raised member raised no further than that needs; hard constraints without e, μ."""
    _, spec, data = qp_subproblem("freeflyer", 2, Window(0, 100, 100), True, True, delta=0.3)
    stage = StageQP(spec)
    qp = stage.build(data)
    N, n, nu = qp.shape
    rng = np.random.default_rng(0)
    state = DualState.empty(qp)
    for z in state:
        z[:, :4] = rng.choice([0.0, -1.0, 1e-9, 3e-3, 0.5, 40.0], size=(len(z), 4))
    before = DualState(state.boxes.copy(), state.rows.copy())
    y = np.zeros((N + 1, n + nu))
    y[:, :n] = data.X_ref / stage.sx
    delta, root = 1e-4, 1e-2
    riccati_kernel.solve(qp, y, np.zeros((N, n)), RiccatiOptions(TOL, GAP_TOL, 0, delta), state)
    b, r = qp.boxes, qp.rows
    gy = (b.sign * y[b.k, b.j], np.sum(r.coef * y[r.k[:, None], r.cols], axis=1))
    for z, z0, g, d, rho in zip(state, before, gy, (b.d, r.d), (b.rho, r.rho), strict=True):
        soft = rho > 0
        assert soft.any() and np.all(z[~soft][:, [E, MU]] == 0.0)
        pairs = [(soft, E, MU, z0[:, E], z0[:, MU]), (np.ones(len(z), bool), S, LAM, d - g + z[:, E], z0[:, LAM])]
        for rows, i, j, a0, b0 in pairs:
            a0, b0 = np.maximum(a0[rows], 0.0), np.maximum(b0[rows], 0.0)
            a, c = z[rows, i], z[rows, j]
            assert np.all(a >= a0) and np.all(c >= b0)
            assert np.all(a * c >= delta * (1 - 1e-12))
            big, new_big = np.maximum(a0, b0), np.where(a0 >= b0, a, c)
            assert np.all(new_big == np.maximum(big, root))
            small, new_small = np.where(a0 >= b0, b0, a0), np.where(a0 >= b0, c, a)
            np.testing.assert_allclose(new_small, np.maximum(small, delta / new_big), rtol=1e-15)


def test_a_warm_start_far_from_feasible_starts_cold() -> None:
    """A warm start whose residual is above ``WARM_RESIDUAL`` (multipliers of 1e3 on every constraint) is dropped
    after its first residual pass for the cold start from the same y, π: the cold solve's iterates to the bit, one
    iteration later."""
    _, spec, data = qp_subproblem("freeflyer", 2, Window(0, 100, 100), True, True, delta=0.3)
    qp = StageQP(spec).build(data)
    N, n, nu = qp.shape
    ys, outs = [], []
    for warm in (0.0, WARM):
        state = DualState.empty(qp)
        for z in state:
            z[:, :4] = 1e3
        y, pi = np.zeros((N + 1, n + nu)), np.zeros((N, n))
        outs.append(riccati_kernel.solve(qp, y, pi, RiccatiOptions(TOL, GAP_TOL, MAX_ITER, warm), state))
        ys.append(y)
    assert outs[0].status == outs[1].status == 0
    assert outs[1].iterations == outs[0].iterations + 1
    assert np.array_equal(ys[0], ys[1])


def test_a_state_that_does_not_fit_is_refused() -> None:
    """A ``DualState`` of another QP (one box short) is a ``ValueError``, not a write past its arrays."""
    _, spec, data = qp_subproblem("freeflyer", 2, Window(0, 100, 100), True, True, delta=0.3)
    qp = StageQP(spec).build(data)
    N, n, nu = qp.shape
    state = DualState.empty(qp)
    short = DualState(state.boxes[1:].copy(), state.rows)
    with pytest.raises(ValueError, match="DualState"):
        riccati_kernel.solve(qp, np.zeros((N + 1, n + nu)), np.zeros((N, n)), RiccatiOptions(TOL, GAP_TOL, 5), short)


def _ip_iterations(results) -> list[int]:
    return [k for r in results for h in r.history if (k := status_iterations(h.solver_status)) is not None]


@pytest.mark.parametrize("name", ["freeflyer", "quadrotor"])
def test_warm_solves_keep_the_cold_optima(monkeypatch, name: str) -> None:
    """REL + SCP warm (the default) and cold: the same statuses and subproblems, costs within 1e-6, fewer
    interior-point iterations in all."""
    sc = get_scenario(name)
    iterations = {}
    results = {}
    for warm in (0.0, WARM):
        monkeypatch.setattr(RiccatiSolver, "warm", warm)
        results[warm] = [solve_problem(sc, sc.sample(np.random.default_rng(seed))) for seed in (0, 1)]
        iterations[warm] = sum(_ip_iterations([r for pair in results[warm] for r in pair]))
    for (rel_c, scp_c), (rel_w, scp_w) in zip(results[0.0], results[WARM], strict=True):
        assert scp_c is not None and scp_w is not None
        for c, w in ((rel_c, rel_w), (scp_c, scp_w)):
            assert (w.status, w.iterations) == (c.status, c.iterations)
            assert w.cost == pytest.approx(c.cost, rel=1e-6)
    assert iterations[WARM] < 0.9 * iterations[0.0], iterations


def test_mpc_windows_start_cold(monkeypatch) -> None:
    """An MPC window's SCP (a soft terminal term) from a perturbed guess: every subproblem as with warm starts off,
    to the bit."""
    sc = get_scenario("freeflyer")
    p = sc.sample(np.random.default_rng(0))
    _, sol = solve_problem(sc, p)
    assert sol is not None
    t, H = 10, 30
    X = sol.X[t : t + H + 1].copy()
    X[1:] += 0.05 * np.asarray(sc.state_scale) * np.random.default_rng(1).standard_normal(X[1:].shape)
    case = (
        SCPProblem(sc, p, Window(t, H, len(sol.U)), TerminalCost(sol.X[t + H], 10.0), soft=True),
        X,
        sol.U[t : t + H],
    )
    warm = solve_scp(*case)
    monkeypatch.setattr(RiccatiSolver, "warm", 0.0)
    cold = solve_scp(*case)
    assert warm.iterations > 1  # (a later subproblem, which a warm start would change)
    assert [h.solver_status for h in warm.history] == [h.solver_status for h in cold.history]
    assert np.array_equal(warm.X, cold.X)
