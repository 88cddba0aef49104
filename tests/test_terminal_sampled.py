"""The ``sampled`` terminal kind (LMPC's sampled terminal set): its cost over the samples' simplex, its rows in the
window's convex subproblem (λ variables, conic solvers only), the samples the kind makes per window, and a short
closed loop on the quadrotor."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import qp_subproblem

from ttompc.mpc.settings import MPCSettings
from ttompc.mpc.terminal import SAMPLES, TERMINALS, SampledTerminal, TargetFilter, terminal_term
from ttompc.scenarios import Window, get_scenario
from ttompc.solvers.backends.conic import AssembledSolver
from ttompc.solvers.backends.riccati import supports
from ttompc.solvers.naive import NaiveCvxpySolver
from ttompc.solvers.sample_hull import hull_cost
from ttompc.solvers.scp import SCPOptions, SCPProblem, TerminalCost, solve_rel, solve_scp


def _value_planner(form: str = "mlp", width: int = 16):
    """A randomly initialised quadrotor planner with a value output of ``form`` (``width`` 0: none)."""
    import torch

    from ttompc.policy import ModelConfig, Planner, TrajectoryGPT
    from ttompc.policy.stats import NormStats

    sc = get_scenario("quadrotor")
    torch.manual_seed(0)
    cfg = ModelConfig(n_embd=32, n_layer=1, n_head=2, max_steps=sc.n_steps, dropout=0.0, value_width=width,
                      value_form=form)  # fmt: skip
    n, m = sc.state_dim, sc.control_dim
    stats = NormStats(
        mean={"states": np.zeros(n), "actions": np.zeros(m), "goals": np.zeros(n), "rtg": [-0.03], "ctg": [5.0]},
        std={"states": np.ones(n), "actions": np.full(m, 0.1), "goals": np.ones(n), "rtg": [0.02], "ctg": [5.0]},
    )
    return Planner(TrajectoryGPT(cfg).eval(), sc, stats)


@pytest.fixture(scope="module")
def window() -> tuple:
    """(scenario, problem, REL solution, window [20, 30), its warm start X, U) on a quadrotor problem."""
    sc = get_scenario("quadrotor")
    p = sc.sample(np.random.default_rng(3))
    rel = solve_rel(sc, p, backend="clarabel")
    assert rel.success
    return sc, p, rel, Window(20, 10, p.n_steps), rel.X[20:31].copy(), rel.U[20:30].copy()


def _solve(setup: tuple, terminal: TerminalCost):
    sc, p, _, w, X, U = setup
    return solve_scp(SCPProblem(sc, p, w, terminal, soft=True), X, U, SCPOptions(backend="clarabel"))


def _brute_force(x: np.ndarray, w: np.ndarray, Z: np.ndarray, c: np.ndarray, steps: int) -> float:
    """min of ‖w(x − Zᵀλ)‖ + cᵀλ over the points of the simplex (K = 2 or 3) whose weights are multiples of
    1/steps."""
    grid = np.arange(steps + 1)
    if len(Z) == 2:
        lam = np.stack([grid, steps - grid], axis=1) / steps
    else:
        i, j = np.meshgrid(grid, grid, indexing="ij")
        keep = i + j <= steps
        lam = np.stack([i[keep], j[keep], steps - i[keep] - j[keep]], axis=1) / steps
    return float(np.min(np.linalg.norm(w * (x - lam @ Z), axis=1) + lam @ c))


def test_the_hull_cost_is_the_minimum_over_the_simplex() -> None:
    """``hull_cost`` (the merit's terminal part) against a fine grid of the simplex on random data: points inside
    the hull (the minimum inside the triangle), outside it (on an edge or a vertex), repeated samples (the padding),
    costs that pull elsewhere. Exact: never above the grid's minimum, below it by at most the grid's resolution."""
    rng = np.random.default_rng(0)
    for trial in range(24):
        n, K = int(rng.integers(2, 7)), int(rng.choice([2, 3]))
        Z, w, c = rng.normal(size=(K, n)), rng.uniform(0.2, 3.0, n), rng.uniform(0.0, 2.0, K) * (trial % 2)
        x = rng.dirichlet(np.ones(K)) @ Z + (0.02 if trial % 3 == 0 else 1.0) * rng.normal(size=n)
        if trial % 4 == 0 and K == 3:
            Z[2], c[2] = Z[1], c[1]
        steps = 600
        exact, grid = hull_cost(x, w, Z, c), _brute_force(x, w, Z, c, steps)
        lipschitz = np.linalg.norm(w[:, None] * Z.T, 2) + np.linalg.norm(c)  # of the objective in λ (2-norm)
        assert grid - lipschitz * np.sqrt(K) / steps <= exact <= grid + 1e-12, trial
    Z = np.eye(3)
    assert hull_cost(np.full(3, 1 / 3), np.ones(3), Z, np.zeros(3)) == pytest.approx(0.0, abs=1e-12)  # interior
    assert hull_cost(np.full(3, 1 / 3), np.ones(3), Z, np.array([1.0, 1.0, 1.0])) == pytest.approx(1.0)


def test_one_sample_at_no_cost_is_the_target_term(window: tuple) -> None:
    """K = 1, c = 0: the sampled set is the paper's target, so the window's SCP (conic backend) gives the target
    kind's solution and merits to solver tolerance."""
    sc, *_ = window
    target = window[2].X[30] + 0.1 * np.asarray(sc.state_scale) * np.random.default_rng(0).normal(size=sc.state_dim)
    a = _solve(window, TerminalCost(target, 2.0))
    b = _solve(window, TerminalCost(target, 2.0, samples=target[None], sample_costs=[0.0]))
    assert a.success and b.success and a.iterations == b.iterations
    np.testing.assert_allclose(b.X, a.X, atol=1e-6)
    np.testing.assert_allclose(b.U, a.U, atol=1e-6)
    merits = [(h.objective, g.objective) for h, g in zip(a.history, b.history, strict=True)]
    assert all(m == pytest.approx(n, rel=1e-6) for m, n in merits)
    assert TerminalCost(target, 2.0, samples=target[None], sample_costs=[0.0])(b.X[-1]) == pytest.approx(
        TerminalCost(target, 2.0)(b.X[-1]), rel=1e-12
    )


def test_a_heavy_weight_ends_on_the_segment_and_toward_the_cheaper_sample(window: tuple) -> None:
    """K = 2 with a heavy weight: the window ends (numerically) on the segment between the samples; making the
    first sample expensive moves the end toward the second."""
    sc, *_ = window
    units = np.asarray(sc.state_scale)
    rng = np.random.default_rng(1)
    mid = window[2].X[30]
    z1, z2 = mid - 0.2 * units * rng.normal(size=6), mid + 0.2 * units * rng.normal(size=6)
    where = []
    for c1 in (0.0, 0.05):
        res = _solve(window, TerminalCost(mid, 1e3, samples=np.stack([z1, z2]), sample_costs=[c1, 0.0]))
        assert res.success
        d = (z2 - z1) / units
        s = float((res.X[-1] - z1) / units @ d / (d @ d))
        off = np.linalg.norm((res.X[-1] - z1) / units - s * d)
        assert -1e-6 <= s <= 1 + 1e-6 and off <= 1e-4 * np.linalg.norm(d), (s, off)
        where.append(s)
    assert where[1] > where[0] + 0.05, where


def _sampled_window(seed: int):
    """(spec, data) of a quadrotor MPC window (H = 10) with a sampled terminal set of 3 samples, one repeated."""
    sc, spec, data = qp_subproblem("quadrotor", 5, Window(20, 10, 100), True, True, delta=0.3)
    spec = dataclasses.replace(spec, terminal="sampled", samples=SAMPLES, tr_states=tuple(range(1, 11)))
    rng = np.random.default_rng(seed)
    units = np.asarray(sc.state_scale)
    Z = data.X_ref[-1] + 0.3 * units * rng.normal(size=(SAMPLES, sc.state_dim))
    Z[2] = Z[0]
    data = dataclasses.replace(
        data,
        terminal_target=Z[0],
        terminal_weights=np.linspace(1.0, 4.0, sc.state_dim),
        terminal_samples=Z,
        terminal_sample_costs=np.array([0.02, 0.0, 0.02]),
    )
    return spec, data


def test_the_merit_reads_the_subproblems_terminal_part() -> None:
    """The sampled rows solved by Clarabel: the optimum is the independent cvxpy model's, λ lies on the simplex, τ
    is ‖W(x_H − Zλ)‖ + cᵀλ, and ``TerminalCost`` (the merit) at the window's end is τ. The riccati kernel does not
    take the structure; the default chain runs it on the conic solvers."""
    from ttompc.solvers.backends.chain import get_solver

    spec, data = _sampled_window(2)
    assert not supports(spec)
    assert isinstance(get_solver(spec, "auto", get_scenario("quadrotor")), AssembledSolver)
    solver = AssembledSolver(spec, ["clarabel"])
    X, _, sol = solver.solve(data)
    _, _, ref = NaiveCvxpySolver(spec).solve(data)
    assert X is not None and sol.ok and ref.ok
    assert sol.objective == pytest.approx(ref.objective, rel=1e-6, abs=1e-8)
    z = sol.z * solver.sub.scale
    tau, lam = z[solver.sub.iterminal[0]], z[solver.sub.iterminal[1:]]
    assert lam.min() >= -1e-8 and lam.sum() == pytest.approx(1.0, abs=1e-8)
    Z, c, w = data.terminal_samples, data.terminal_sample_costs, data.terminal_weights
    assert tau == pytest.approx(np.linalg.norm(w * (X[-1] - lam @ Z)) + c @ lam, rel=1e-6, abs=1e-8)
    merit = TerminalCost(data.terminal_target, w, samples=Z, sample_costs=c)(X[-1])
    assert merit == pytest.approx(tau, rel=1e-6, abs=1e-8)
    assert merit > 1e-3  # the end is not in the hull: the cone is active


def test_the_kind_samples_the_rel_plan_the_models_end_and_the_previous_end(window: tuple) -> None:
    """Per window ending at k: the model's end x̂ at V(x̂, k), the REL plan's state at its remaining stage cost
    (both times mpc.fuel, soft mode), and from the second consecutive window on the previous end moved on by the new
    plan's last step at its V; always SAMPLES columns (the first repeated). The target stays the model's end."""
    sc, p, *_ = window
    planner = _value_planner()
    kind = terminal_term(MPCSettings(terminal="sampled", track=2.5), 0.0, planner)
    assert isinstance(kind, SampledTerminal)
    kind.reset(sc, p)
    rel = solve_rel(sc, p)
    value = planner.value_model()
    X1 = rel.X[5:16] + 0.01
    t1 = kind(sc, Window(5, 10, p.n_steps), X1)
    assert t1 is not None and t1.samples is not None and t1.sample_costs is not None
    assert t1.samples.shape == (SAMPLES, sc.state_dim) and np.array_equal(t1.target, X1[-1])
    assert np.allclose(t1.weights, 2.5) and np.array_equal(t1.samples[2], t1.samples[0])
    v1 = kind.values.at(15)(X1[-1])
    assert v1 == pytest.approx(value.expand(sc.model_goal(p), X1[-1], 15, np.eye(6)).value)
    np.testing.assert_allclose(t1.samples[1], rel.X[15], atol=1e-6)
    np.testing.assert_allclose(t1.sample_costs[:2], sc.mpc.fuel * np.array([v1, sc.cost(rel.U[15:])]), rtol=1e-6)
    X2 = rel.X[6:17] - 0.01
    t2 = kind(sc, Window(6, 10, p.n_steps), X2)
    assert t2 is not None and t2.samples is not None and t2.sample_costs is not None
    moved = X1[-1] + X2[-1] - X2[-2]
    np.testing.assert_allclose(t2.samples[2], moved)
    assert t2.sample_costs[2] == pytest.approx(sc.mpc.fuel * kind.values.at(16)(moved))
    t3 = kind(sc, Window(8, 10, p.n_steps), X2)  # not the next window: no previous end
    assert t3 is not None and t3.samples is not None and np.array_equal(t3.samples[2], t3.samples[0])
    assert kind(sc, Window(90, 10, p.n_steps), rel.X[90:]) is None  # the end: the loop's end condition


def test_settings_registry_and_refusals_name_the_sampled_kind() -> None:
    """``terminal=sampled`` is a registered setting; it needs a value output (either form), methods without a
    model keep the target, DAgger's rollouts refuse it, and reports list its departure first."""
    from ttompc.config import ConfigError
    from ttompc.finetune.config import check_rollout_settings
    from ttompc.mpc.settings import departures

    sc = get_scenario("quadrotor")
    assert TERMINALS["sampled"] is SampledTerminal and not SampledTerminal.rollouts
    assert isinstance(terminal_term(MPCSettings(terminal="sampled")), TargetFilter)  # PLAN-ONCE, ORACLE-MPC
    plain = _value_planner(width=0)
    assert not plain.has_value and "value output" in str(SampledTerminal.refusal(plain))
    with pytest.raises(ConfigError, match="terminal=sampled"):
        terminal_term(MPCSettings(terminal="sampled"), 0.0, plain)
    for form in ("mlp", "gauss_newton"):
        assert SampledTerminal.refusal(_value_planner(form)) is None
    with pytest.raises(ConfigError, match="terminal"):
        check_rollout_settings(MPCSettings(terminal="sampled"))
    notes = departures(MPCSettings(terminal="sampled", track=sc.mpc.terminal), sc)
    assert len(notes) == 1 and notes[0].startswith("terminal sampled")


def test_a_short_closed_loop_with_the_sampled_terminal_runs_and_reports(monkeypatch: pytest.MonkeyPatch) -> None:
    """``evaluate mpc``'s measurement with ``mpc.terminal=sampled`` on one quadrotor problem for a few steps: the
    model method's windows solve sampled-set subproblems (3 columns) and the loop reports its metrics."""
    from ttompc.evaluation.episodes import closed_loop_metrics
    from ttompc.evaluation.measurement import Measurement
    from ttompc.solvers import engine

    specs = []
    get_solver = engine.get_solver

    def recording(spec, backend, scenario=None):
        specs.append(spec)
        return get_solver(spec, backend, scenario)

    monkeypatch.setattr(engine, "get_solver", recording)
    planner = _value_planner("gauss_newton")
    m = Measurement(protocol="recommended", mpc={"terminal": "sampled"}, problems=1, seed=1001, max_steps=4)
    assert m.settings.terminal == "sampled"
    problems = m.problem_set(planner.scenario)
    specs.clear()
    metrics, [ep] = closed_loop_metrics(planner, m, problems)
    windows = [s for s in specs if s.terminal == "sampled"]
    assert len(windows) >= 4 and all(s.samples == SAMPLES and not supports(s) for s in windows)
    assert len(ep.step_times) == 4 and ep.iterations.min() >= 1 and np.isfinite(ep.target_change)
    assert set(metrics) >= {"feasible_rate", "cost_increment", "step_time_mean", "fallbacks"}
    assert metrics["step_time_mean"] > 0
