"""SCP engine properties: feasibility of solutions, REL lower bound, determinism, agreement of the assembled
subproblem with an independent cvxpy formulation, the reference formulation, error handling."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from ttompc.scenarios import BlockKind, ConstraintBlock, Window, get_scenario
from ttompc.solvers import SCPOptions, SCPProblem, SCPStatus, TerminalCost, solve_problem, solve_rel, solve_scp
from ttompc.solvers.backends.conic import AssembledSolver
from ttompc.solvers.naive import NaiveCvxpySolver
from ttompc.solvers.spec import SubproblemData, SubproblemSpec


@pytest.fixture(scope="module")
def ff():
    return get_scenario("freeflyer")


@pytest.fixture(scope="module")
def solved(ff):
    out = []
    for seed in (0, 2, 7):
        p = ff.sample(np.random.default_rng(seed))
        out.append((p, *solve_problem(ff, p)))
    return out


def test_solutions_satisfy_the_nonlinear_problem(ff, solved) -> None:
    for p, rel, scp in solved:
        assert rel.success and scp.success
        X, U = scp.X, scp.U
        np.testing.assert_allclose(X[0], p.x0, atol=1e-9)
        np.testing.assert_allclose(X[-1], p.goal, atol=1e-6)
        np.testing.assert_allclose(ff.rollout(p, U), X, atol=1e-6)  # exact dynamics from x0
        assert ff.violations(p, X).sum() == 0
        assert ff.path_violation(p, X, U, Window.full(p)) <= 1e-6  # clearance, table, thruster bound
        assert scp.violation <= ff.scp.feas_tol


def test_rel_is_a_lower_bound(solved) -> None:
    for _, rel, scp in solved:
        assert rel.cost <= scp.cost + 1e-7


def test_rel_violates_obstacles_on_a_nonconvex_problem(ff, solved) -> None:
    # seed 0's straight REL path crosses an obstacle: the non-convexity factor (ctg0) is positive
    p, rel, scp = solved[0]
    assert ff.violations(p, rel.X[:-1]).sum() > 0
    assert scp.cost > rel.cost * 1.01


def test_history_and_best_iterate(ff, solved) -> None:
    """The returned iterate is the latest feasible one whose merit is within the stopping rule's tolerance of the
    lowest feasible merit."""
    tol = ff.scp.cost_tol
    for _, _, scp in solved:
        assert len(scp.history) == scp.iterations >= 1
        feasible = [h for h in scp.history if h.violation <= ff.scp.feas_tol]
        lowest = min(h.objective for h in feasible)
        best = [h for h in feasible if h.objective <= lowest + tol][-1]
        assert scp.best_iteration == best.iteration and scp.cost == pytest.approx(best.cost, abs=1e-12)
        radii = [h.trust_radius for h in scp.history]
        assert all(b < a for a, b in itertools.pairwise(radii))  # geometric shrink


def test_merits_within_the_tolerance_count_as_equal() -> None:
    """Iterates of a flat valley (merits within ``tie_tol``, e.g. a window with several optima) return the latest, so
    rounding below the stopping rule's tolerance cannot pick one; a merit lower by more than it wins; infeasible
    iterates never do."""
    from ttompc.solvers.engine import _Iterates
    from ttompc.solvers.results import IterateRecord

    def record(it: int, merit: float, violation: float = 0.0) -> IterateRecord:
        return IterateRecord(it, merit, merit, violation, 0.0, 1.0, 0.0, "ok")

    def best(merits: list[tuple[float, float]]) -> int:
        iterates = _Iterates(feas_tol=1e-4, tie_tol=1e-6)
        for it, (merit, violation) in enumerate(merits):
            iterates.add(record(it, merit, violation), np.full((2, 1), it), np.full((1, 1), it))
        assert iterates.best is not None and iterates.best[0][0, 0] == iterates.best[3]
        return iterates.best[3]

    assert best([(1.0, 0), (1.0 + 5e-7, 0)]) == 1  # a tie: the latest
    assert best([(1.0, 0), (1.0 - 5e-7, 0)]) == 1
    assert best([(1.0, 0), (1.0 + 2e-6, 0)]) == 0  # worse by more than the tolerance
    assert best([(1.0, 0), (0.5, 1.0)]) == 0  # infeasible
    # ties are measured from the lowest merit, so a slow climb by less than the tolerance per iterate stops
    assert best([(1.0, 0), (1.0 + 6e-7, 0), (1.0 + 1.2e-6, 0)]) == 1


def test_deterministic(ff) -> None:
    p1 = ff.sample(np.random.default_rng(11))
    p2 = ff.sample(np.random.default_rng(11))
    a = solve_problem(ff, p1)[1]
    b = solve_problem(ff, p2)[1]
    np.testing.assert_array_equal(a.U, b.U)


def test_a_result_prints_as_one_short_line(solved) -> None:
    scp = solved[0][2]
    text = repr(scp)
    assert text == str(scp) and "\n" not in text and len(text) < 160 and "array" not in text, text
    assert text.startswith(f"SCPResult({scp.status.value}, cost={scp.cost:.6g}, iterations={scp.iterations},")
    assert "X(101, 6), U(100, 3)" in text


# the Riccati kernel's cached stage maps (the default), PIQP's cached QP, Clarabel's cached conic problem
@pytest.mark.parametrize(("name", "backend"), [("freeflyer", "auto"), ("freeflyer", "piqp"), ("rpod", "auto")])
def test_a_solve_does_not_depend_on_earlier_solves(name: str, backend: str) -> None:
    """Solvers are cached per structure and process; a problem solved after another one (a pool worker's second
    task) gives the bits of the same problem solved first (a fresh worker), so regenerated data rows are exact."""
    from ttompc.seeding import problem_seed
    from ttompc.solvers.backends import clear_solver_cache

    scenario = get_scenario(name)
    earlier, problem = (scenario.sample(np.random.default_rng(problem_seed(0, i))) for i in (1, 0))
    clear_solver_cache()
    fresh = solve_problem(scenario, problem, backend=backend)
    clear_solver_cache()
    solve_problem(scenario, earlier, backend=backend)
    after = solve_problem(scenario, problem, backend=backend)
    for a, b in zip(fresh, after, strict=True):
        assert a is not None and b is not None
        np.testing.assert_array_equal(a.X, b.X)
        np.testing.assert_array_equal(a.U, b.U)
        assert a.iterations == b.iterations


@pytest.mark.parametrize("terminal", ["hard", "soft"])
@pytest.mark.parametrize("trust", ["l2", "linf"])
def test_assembled_subproblem_matches_cvxpy(ff, terminal, trust) -> None:
    """The sparse assembly and a per-timestep cvxpy model of the same subproblem have the same optimum."""
    rng = np.random.default_rng(3)
    p = ff.sample(rng)
    w = Window(0, 30, 100) if terminal == "soft" else Window(70, 30, 100)
    X, U = ff.initial_guess(p, w)
    X = X + rng.normal(scale=0.05, size=X.shape)
    blocks = ff.constraints(p, w, X, U, obstacles=True)
    # an extra equality (waypoint-like) to exercise soft equalities and penalised EQ rows
    Gx = np.zeros((1, 2, 6))
    Gx[0, 0, 0] = Gx[0, 1, 1] = 1.0
    blocks.append(ConstraintBlock("wp", BlockKind.EQ, np.array([15]), Gx, None, X[15:16, :2] + 0.01, weight=0.7))
    for soft_eq in (False, True):
        spec = SubproblemSpec(
            H=w.length,
            n=6,
            m=3,
            cost_norm="l1",
            fuel_weight=1.0,
            penalized=True,
            virtual_control=True,
            trust=trust,
            end_form=terminal,
            soft_equalities=soft_eq,
            penalty=100.0,
            blocks=tuple(SubproblemSpec.block_signature(b) for b in blocks),
            tr_states=tuple(range(1, w.length + (0 if terminal == "hard" else 1))),
        )
        data = SubproblemData(
            x_start=X[0],
            model=ff.convex_model(p, w, X, U),
            blocks=blocks,
            X_ref=X,
            delta=0.2,
            goal=p.goal,
            terminal_target=X[-1] + 0.1 if terminal == "soft" else None,
            terminal_weights=np.array([1, 1, 1, 7, 7, 7.0]) if terminal == "soft" else None,
        )
        _, _, ours = AssembledSolver(spec, ["clarabel"]).solve(data)
        _, _, ref = NaiveCvxpySolver(spec).solve(data)
        assert ours.ok and ref.ok
        assert ours.objective == pytest.approx(ref.objective, rel=1e-5, abs=1e-7)


def test_backends_agree(ff) -> None:
    p = ff.sample(np.random.default_rng(4))
    a = solve_rel(ff, p, backend="clarabel")
    b = solve_rel(ff, p, backend="qoco")
    assert a.success and b.success
    assert a.cost == pytest.approx(b.cost, rel=1e-5)


def test_reference_formulation_is_selectable_and_gives_up(ff) -> None:
    """Seed 15: the reference's hard linearised constraints make a subproblem infeasible (docs/benchmarks.md), the
    penalized formulation solves the same problem."""
    p = ff.sample(np.random.default_rng(15))
    rel = solve_rel(ff, p)
    ref = solve_scp(SCPProblem(ff, p), rel.X, rel.U, SCPOptions(formulation="reference"))
    ours = solve_scp(SCPProblem(ff, p), rel.X, rel.U)
    assert ref.status is SCPStatus.INFEASIBLE and not ref.success
    assert ours.success and ours.violation <= ff.scp.feas_tol


def test_mpc_window_with_terminal_cost(ff) -> None:
    p = ff.sample(np.random.default_rng(5))
    rel = solve_rel(ff, p)
    w = Window(0, 20, 100)
    X0, U0 = rel.X[:21], rel.U[:20]
    res = solve_scp(SCPProblem(ff, p, w, TerminalCost(rel.X[20], ff.mpc.target)), X0, U0)
    assert res.success and res.X.shape == (21, 6)
    assert np.linalg.norm(res.X[-1] - rel.X[20]) < 0.05  # pulled to the REL state at t+H


class _Quadratic:
    """An exact quadratic cost-to-go J(x) = ½ k‖x − c‖² + gᵀx (a ``TerminalValue``), recording its expansions."""

    def __init__(self, k: float, c: np.ndarray, g: np.ndarray) -> None:
        self.k, self.c, self.g, self.at = k, c, g, []

    def __call__(self, x: np.ndarray) -> float:
        return float(0.5 * self.k * np.sum((x - self.c) ** 2) + self.g @ x)

    def expand(self, x: np.ndarray) -> object:
        from ttompc.policy.value import ValueExpansion

        self.at.append(np.array(x))
        n = len(x)
        return ValueExpansion(self(x), self.k * (x - self.c) + self.g, self.k * np.eye(n))


def test_mpc_window_with_a_cost_to_go_pays_its_local_model(ff) -> None:
    """A window whose terminal cost is a cost-to-go J alone (``TerminalCost.value``, no 2-norm term): each SCP
    iteration pays J's local model about its reference end state (the expansion points are the previous iterates'
    x_H), the accepted iterates' objectives read J itself, and the optimum moves with J: a steeper J pulls x_H to
    its centre (the distance falling ~1/k), a linear term moves x_H against it."""
    p = ff.sample(np.random.default_rng(5))
    rel = solve_rel(ff, p)
    w = Window(0, 20, 100)
    X0, U0 = rel.X[:21], rel.U[:20]
    c, n = rel.X[20] + np.array([0.05, -0.05, 0.0, 0.0, 0.0, 0.0]), ff.state_dim
    gaps = []
    for k in (1.0, 10.0, 100.0):
        J = _Quadratic(k, c, np.zeros(n))
        res = solve_scp(SCPProblem(ff, p, w, TerminalCost(c, 0.0, value=J)), X0, U0)
        assert res.success
        np.testing.assert_allclose(J.at[0], X0[-1])  # the first model is about the warm start's end state
        assert len(J.at) == len(res.history)  # one expansion per iteration
        last = res.history[res.best_iteration]
        assert last.objective == pytest.approx(ff.cost(res.U) * 1.0 + J(res.X[-1]), rel=1e-6, abs=1e-9)
        gaps.append(float(np.linalg.norm(res.X[-1] - c)))
    assert gaps[0] > gaps[1] > gaps[2] and gaps[2] < 0.2 * gaps[0]
    pushed = solve_scp(SCPProblem(ff, p, w, TerminalCost(c, 0.0, value=_Quadratic(100.0, c, np.eye(n)[0]))), X0, U0)
    assert pushed.X[-1][0] < c[0] - 1e-3  # gᵀx with g = e_0 pays for x_0: the end moves toward −e_0
    with pytest.raises(ValueError, match="weights > 0 or a value"):
        TerminalCost(c, 0.0)


def test_bad_inputs_raise_clear_errors(ff) -> None:
    p = ff.sample(np.random.default_rng(6))
    X, U = ff.initial_guess(p)
    full = SCPProblem(ff, p)
    with pytest.raises(ValueError, match=r"warm start must have shapes \(101, 6\) and \(100, 3\)"):
        solve_scp(full, X[:50], U)
    with pytest.raises(ValueError, match="needs a terminal cost"):
        SCPProblem(ff, p, Window(0, 10, 100))
    with pytest.raises(ValueError, match="needs a terminal cost"):  # an update is checked as a new description is
        full.update(window=Window(0, 10, 100))
    with pytest.raises(ValueError, match="unknown SCP formulation"):
        SCPOptions(formulation="nope")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="unknown solver backend"):
        solve_scp(full, X, U, SCPOptions(backend="nope"))
    X_bad = X.copy()
    X_bad[3, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        solve_scp(full, X_bad, U)


def test_converged_warm_start_costs_one_subproblem(ff, solved) -> None:
    """The stopping rule compares the first iterate with the warm start: restarting from an SCP optimum is a fixed
    point found in one subproblem, at the same cost; a far-off warm start still iterates."""
    p, _, scp = solved[1]
    again = solve_scp(SCPProblem(ff, p), scp.X, scp.U)
    assert again.success and again.iterations == 1
    assert again.cost == pytest.approx(scp.cost, rel=1e-6)
    X0, U0 = ff.initial_guess(p)
    assert solve_scp(SCPProblem(ff, p), X0, U0).iterations > 1


def test_rel_from_a_guess(ff) -> None:
    """A REL solution as the guess (e.g. the previous MPC step's plan) is a fixed point: one subproblem, same cost;
    a guess of the wrong shape is refused by name."""
    p = ff.sample(np.random.default_rng(9))
    rel = solve_rel(ff, p)
    again = solve_rel(ff, p, guess=(rel.X, rel.U))
    assert rel.iterations >= 2 and again.iterations == 1
    assert again.cost == pytest.approx(rel.cost, rel=1e-6)
    with pytest.raises(ValueError, match="REL guess must have shapes"):
        solve_rel(ff, p, guess=(rel.X[:-1], rel.U))


def test_costates_are_the_gradient_of_the_optimal_cost_to_go() -> None:
    """``SCPResult.costates`` (the kernel's dynamics multipliers of the returned iterate's subproblem) are
    ∂J*/∂x_k: against central differences of the optimal cost-to-go re-solved from a perturbed x_k."""
    sc = get_scenario("quadrotor")
    p = sc.sample(np.random.default_rng(3))
    _, full = solve_problem(sc, p)
    assert full is not None and full.costates is not None and np.isnan(full.costates[0]).all()
    N, k = p.n_steps, 88
    res = solve_scp(SCPProblem(sc, p, Window(k - 1, N - k + 1, N)), full.X[k - 1 :], full.U[k - 1 :])
    assert res.costates is not None and res.costates.shape == (N - k + 2, sc.state_dim)

    def cost_to_go(x: np.ndarray) -> float:
        X0 = full.X[k:].copy()
        X0[0] = x
        return sc.cost(solve_scp(SCPProblem(sc, p, Window(k, N - k, N)), X0, full.U[k:]).U)

    units = sc.state_units()
    fd = np.array(
        [
            (cost_to_go(full.X[k] + 1e-4 * u * e) - cost_to_go(full.X[k] - 1e-4 * u * e)) / (2e-4 * u)
            for e, u in zip(np.eye(sc.state_dim), units, strict=True)
        ]
    )
    np.testing.assert_allclose(res.costates[1], fd, rtol=0.02, atol=1e-3 * np.abs(fd).max())


def test_costates_map_to_the_models_representation() -> None:
    """``model_costates``: ∂J/∂s = (∂x/∂s)ᵀ ∂J/∂x for RPOD's ROE -> RTN map: a first-order change of J along δs is
    the same in both representations."""
    from ttompc.data.schema import model_costates

    sc = get_scenario("rpod")
    p = sc.sample(np.random.default_rng(0))
    rng = np.random.default_rng(1)
    lam_x, ds = rng.normal(size=(5, 6)), rng.normal(size=(5, 6))
    lam_s = model_costates(sc, p, lam_x)
    dx = sc.from_model_states(p, ds)
    np.testing.assert_allclose(np.sum(lam_s * ds, axis=1), np.sum(lam_x * dx, axis=1), rtol=1e-10)
