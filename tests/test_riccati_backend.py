"""The Riccati interior-point backend (first in the default chain, ``backend="auto"``): its kernel against a dense KKT
solve and Clarabel on small stage QPs, its stage-wise form against PIQP on the engine's subproblems, its terminal cone
(MPC windows) against Clarabel and cvxpy, whole REL + SCP solves against the PIQP path (``backend="piqp"``), the
fallback, and where the chain takes it."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cvxpy as cp
import numpy as np
import pytest
from helpers import qp_subproblem, waypoint_subproblem

from ttompc.scenarios import Window, get_scenario
from ttompc.solvers import SCPOptions, SCPProblem, TerminalCost, solve_problem, solve_scp
from ttompc.solvers.backends import backend_chain, get_solver
from ttompc.solvers.backends import riccati as riccati_module
from ttompc.solvers.backends.conic import AssembledSolver
from ttompc.solvers.backends.qp import PIQPSolver
from ttompc.solvers.backends.riccati import RiccatiSolver, StageQP, supports
from ttompc.solvers.backends.riccati_qp import (
    Boxes,
    Dynamics,
    RiccatiOptions,
    RiccatiResult,
    Rows,
    StageCost,
    StageQPData,
    TerminalCone,
)
from ttompc.solvers.spec import QuadraticTerminalCost, SubproblemData, SubproblemSpec


def _random_stage_qp(seed: int, N: int = 6, n: int = 3, nu: int = 2) -> tuple[Dynamics, StageCost]:
    rng = np.random.default_rng(seed)
    A = np.eye(n) + 0.1 * rng.normal(size=(N, n, n))
    B = rng.normal(size=(N, n, nu))
    c = 0.1 * rng.normal(size=(N, n))
    Qd = rng.uniform(0.5, 2.0, size=(N + 1, n + nu))
    q = rng.normal(size=(N + 1, n + nu))
    return Dynamics(A, B, c, rng.normal(size=n)), StageCost(Qd, q)


TIGHT = RiccatiOptions(tol=1e-10, gap_tol=1e-11, max_iter=100)
# with the cone, the engine's tolerances: at TIGHT's the kernel ends within 100× them for some seeds (status 3)
ENGINE = RiccatiOptions(tol=riccati_module.TOL, gap_tol=riccati_module.GAP_TOL, max_iter=riccati_module.MAX_ITER)


def _kernel(qp: StageQPData, options: RiccatiOptions = TIGHT) -> tuple[RiccatiResult, np.ndarray, np.ndarray]:
    """The kernel's solve of ``qp`` from y = 0, π = 0: (result, y, π)."""
    from ttompc.solvers.backends.riccati_kernel import solve

    N, n, nu = qp.shape
    y, pi = np.zeros((N + 1, n + nu)), np.zeros((N, n))
    out = solve(qp, y, pi, options)
    return out, y, pi


def _constraints(seed: int, N: int, n: int) -> tuple[Boxes, Rows]:
    """Hard boxes |x[0]| ≤ 0.4 on stages 1..N, soft ones 0.7·|u[0]| (an L1 term), soft two-variable rows."""
    rng = np.random.default_rng(seed)
    ks = np.repeat(np.arange(1, N + 1), 2)
    boxes = Boxes(
        k=np.concatenate([ks, np.arange(N), np.arange(N)]),
        j=np.concatenate([np.zeros(2 * N, np.int64), np.full(N, n), np.full(N, n)]),
        sign=np.concatenate([np.tile([1.0, -1.0], N), np.ones(N), -np.ones(N)]),
        d=np.concatenate([np.full(2 * N, 0.4), np.zeros(2 * N)]),
        rho=np.concatenate([np.zeros(2 * N), np.full(2 * N, 0.7)]),
    )
    rows = Rows(
        k=np.arange(1, N),
        cols=np.tile([1, 2], (N - 1, 1)),
        coef=rng.normal(size=(N - 1, 2)),
        d=rng.uniform(-0.2, 0.2, size=N - 1),
        rho=np.full(N - 1, 3.0),
    )
    return boxes, rows


def _cvxpy_solve(qp: StageQPData) -> tuple[float, np.ndarray]:
    """An independent cvxpy model of ``qp`` (the ``riccati_qp`` problem) solved by Clarabel: (objective, y)."""
    dyn, cost, b, r, cone = qp.dynamics, qp.cost, qp.boxes, qp.rows, qp.cone
    N, n, nu = qp.shape
    Y = cp.Variable((N + 1, n + nu))
    free = 1 if len(cone.w) else 0  # τ, stage N's first dummy control, is the cone's epigraph variable
    cons = [Y[0, :n] == dyn.x0, Y[N, n + free :] == 0]
    cons += [Y[k + 1, :n] == dyn.A[k] @ Y[k, :n] + dyn.B[k] @ Y[k, n:] + dyn.c[k] for k in range(N)]
    cons += [b.sign[i] * Y[b.k[i], b.j[i]] <= b.d[i] for i in range(len(b.k)) if b.rho[i] == 0]
    cons += [r.coef[i] @ Y[r.k[i], r.cols[i]] <= r.d[i] for i in range(len(r.k)) if r.rho[i] == 0]
    if free:
        cons += [cp.SOC(Y[N, n], cp.multiply(cone.w, Y[N, :n] - cone.center))]
    obj = 0.5 * cp.sum(cp.multiply(cost.Qd, cp.square(Y))) + cp.sum(cp.multiply(cost.q, Y))
    if cost.QN.size:
        obj += 0.5 * cp.quad_form(Y[N, :n], cp.psd_wrap(cost.QN))
    obj += sum(b.rho[i] * cp.pos(b.sign[i] * Y[b.k[i], b.j[i]] - b.d[i]) for i in range(len(b.k)) if b.rho[i] > 0)
    obj += sum(r.rho[i] * cp.pos(r.coef[i] @ Y[r.k[i], r.cols[i]] - r.d[i]) for i in range(len(r.k)) if r.rho[i] > 0)
    problem = cp.Problem(cp.Minimize(obj), cons)
    problem.solve(solver=cp.CLARABEL, tol_gap_abs=1e-10, tol_gap_rel=1e-10, tol_feas=1e-10)
    assert problem.status == cp.OPTIMAL, problem.status
    return float(problem.value), Y.value


def test_kernel_without_constraints_is_the_kkt_solution() -> None:
    """No inequalities: one Newton step; the dense KKT system of the equality-constrained QP gives the same y."""
    n, nu, N = 3, 2, 6
    dyn, cost = _random_stage_qp(0, N, n, nu)
    out, y, _ = _kernel(StageQPData(dyn, cost))
    assert out.status == 0
    A, B, c, x0 = dyn.A, dyn.B, dyn.c, dyn.x0
    # dense KKT over z = [y_0 .. y_N] (the last stage's u is the kernel's dummy: fixed to 0 here too)
    ny, nz = n + nu, (N + 1) * (n + nu)
    H, g = np.diag(cost.Qd.ravel()), cost.q.ravel().copy()
    E, e = [], []
    for k in range(N):  # x_{k+1} − A x_k − B u_k = c_k
        row = np.zeros((n, nz))
        row[:, k * ny : k * ny + n] = -A[k]
        row[:, k * ny + n : (k + 1) * ny] = -B[k]
        row[:, (k + 1) * ny : (k + 1) * ny + n] = np.eye(n)
        E.append(row)
        e.append(c[k])
    fix = np.zeros((n + nu, nz))
    fix[:n, :n] = np.eye(n)
    fix[n:, N * ny + n :] = np.eye(nu)
    E.append(fix)
    e.append(np.concatenate([x0, np.zeros(nu)]))
    E, e = np.vstack(E), np.concatenate(e)
    kkt = np.block([[H, E.T], [E, np.zeros((len(e), len(e)))]])
    z = np.linalg.solve(kkt, np.concatenate([-g, e]))[:nz]
    np.testing.assert_allclose(y.ravel(), z, atol=1e-8)


def test_kernel_with_boxes_and_soft_rows_matches_clarabel() -> None:
    """Hard boxes, soft boxes (an L1 term) and soft two-variable rows: the optimum of an independent cvxpy model."""
    n, nu, N = 3, 2, 6
    dyn, cost = _random_stage_qp(1, N, n, nu)
    boxes, rows = _constraints(2, N, n)
    qp = StageQPData(dyn, cost, boxes, rows)
    out, y, _ = _kernel(qp)
    assert out.status == 0
    value, Y = _cvxpy_solve(qp)
    np.testing.assert_allclose(y, Y, atol=1e-5)
    assert qp.objective(y) == pytest.approx(value, rel=1e-6)
    assert np.max(np.abs(y[1:, 0])) <= 0.4 + 1e-9  # the hard boxes hold
    assert np.isclose(np.max(np.abs(y[1:, 0])), 0.4)  # and one of them is active


def _terminal_block(seed: int, n: int) -> np.ndarray:
    """A dense symmetric PSD (n, n) block of rank n − 1 (semidefinite, not definite)."""
    M = np.random.default_rng(seed).normal(size=(n, n - 1))
    return M @ M.T


def _with_cone(cost: StageCost, seed: int, n: int) -> tuple[StageCost, TerminalCone]:
    """τ = y[N, n] priced at 1 with no Qd (the kernel's contract), the other dummy controls' cost as before, and a
    cone τ ≥ ‖w∘(x_N − center)‖₂ that binds (its centre away from the unconstrained optimum)."""
    rng = np.random.default_rng(seed)
    Qd, q = cost.Qd.copy(), cost.q.copy()
    Qd[-1, n:], q[-1, n:] = 1.0, 0.0
    Qd[-1, n], q[-1, n] = 0.0, 1.0
    return StageCost(Qd, q), TerminalCone(w=rng.uniform(0.5, 3.0, n), center=rng.normal(size=n))


def _boxed_qp(seed: int, cone: bool, n: int, nu: int, N: int) -> tuple[StageQPData, TerminalCone | None]:
    """A random stage QP with hard and soft boxes and soft rows (seeds ``seed``..``seed + 2``), with the terminal
    cone or without; returns it and its cone."""
    dyn, cost = _random_stage_qp(seed, N, n, nu)
    qp = StageQPData(dyn, cost, *_constraints(seed + 1, N, n))
    if not cone:
        return qp, None
    cost, tc = _with_cone(cost, seed + 2, n)
    return qp._replace(cost=cost, cone=tc), tc


@pytest.mark.parametrize("cone", [False, True])
def test_kernel_dense_terminal_block_matches_cvxpy(cone) -> None:
    """A dense PSD terminal block QN with the linear term q[N], under hard and soft boxes and soft rows, with and
    without the terminal cone: the kernel's optimum is the independent cvxpy model's (objective and solution)."""
    n, nu, N = 3, 2, 6
    qp, tc = _boxed_qp(3, cone, n, nu, N)
    qp = qp._replace(cost=StageCost(qp.cost.Qd, qp.cost.q, 4.0 * _terminal_block(6, n)))
    options = ENGINE if cone else TIGHT
    out, y, _ = _kernel(qp, options)
    assert out.status == 0, out
    value, Y = _cvxpy_solve(qp)
    assert qp.objective(y) == pytest.approx(value, rel=1e-6)
    np.testing.assert_allclose(y, Y, atol=1e-5)
    # the block matters: without it the optimum moves
    _, y0, _ = _kernel(qp._replace(cost=StageCost(qp.cost.Qd, qp.cost.q)), options)
    assert np.max(np.abs(y0[-1, :n] - y[-1, :n])) > 1e-2
    if tc is not None:  # the cone binds: τ is the norm, not 0
        assert y[-1, n] == pytest.approx(np.linalg.norm(tc.w * (y[-1, :n] - tc.center)), abs=1e-7)
        assert y[-1, n] > 1e-2


@pytest.mark.parametrize("cone", [False, True])
def test_kernel_zero_terminal_block_is_no_block(cone) -> None:
    """QN = 0 (n, n) is the kernel without a terminal block (QN empty, the default) to the last bit."""
    n, nu, N = 3, 2, 6
    qp, _ = _boxed_qp(7, cone, n, nu, N)
    options = ENGINE if cone else TIGHT
    out, y, pi = _kernel(qp, options)
    out0, y0, pi0 = _kernel(qp._replace(cost=StageCost(qp.cost.Qd, qp.cost.q, np.zeros((n, n)))), options)
    assert out.status == 0 and out == out0
    assert y.tobytes() == y0.tobytes() and pi.tobytes() == pi0.tobytes()


CASES = [
    ("freeflyer", Window(0, 100, 100), True),
    ("freeflyer", Window(0, 100, 100), False),
    ("freeflyer", Window(60, 40, 100), True),
    ("quadrotor", Window(0, 100, 100), True),
    ("quadrotor", Window(0, 100, 100), False),
]


@pytest.mark.parametrize(("name", "window", "obstacles"), CASES)
def test_stage_form_matches_piqp(name, window, obstacles) -> None:
    sc, spec, data = qp_subproblem(name, 3, window, obstacles, True, delta=0.3)
    assert supports(spec)
    X, U, sol = RiccatiSolver(spec).solve(data)
    _, Up, ref = PIQPSolver(spec).solve(data)
    assert sol.ok and sol.status.startswith("RICCATI_SOLVED"), sol.status
    assert sol.objective == pytest.approx(ref.objective, rel=1e-6, abs=1e-9)
    assert sc.cost(U) == pytest.approx(sc.cost(Up), rel=1e-5, abs=1e-8)
    # a solution of the subproblem: initial state, dynamics on the rows without virtual control, trust region
    np.testing.assert_allclose(X[0], data.x_start, atol=1e-12)
    m = data.model
    exact = np.setdiff1d(np.arange(6), spec.virtual_rows()) if spec.virtual_control else np.arange(6)
    pred = np.einsum("hij,hj->hi", m.A, X[:-1]) + np.einsum("hij,hj->hi", m.B, U) + m.c
    np.testing.assert_allclose(X[1:, exact], pred[:, exact], atol=1e-7)
    assert np.max(np.abs(X[1:-1] - data.X_ref[1:-1])) <= data.delta + 1e-7


def test_penalised_equality_rows_match_piqp() -> None:
    spec, data, _ = waypoint_subproblem(penalized=True)
    _, _, sol = RiccatiSolver(spec).solve(data)
    _, _, ref = PIQPSolver(spec).solve(data)
    assert sol.ok and sol.objective == pytest.approx(ref.objective, rel=1e-6)


@pytest.mark.parametrize("name", ["freeflyer", "quadrotor"])
def test_rel_and_scp_take_the_piqp_paths_iterates(name) -> None:
    """Whole solves by the default path: the same number of subproblems and the same costs as the PIQP path
    (``backend="piqp"``), feasible."""
    sc = get_scenario(name)
    for seed in (1, 2):
        p = sc.sample(np.random.default_rng(seed))
        rel_a, scp_a = solve_problem(sc, p, backend="piqp")
        rel_r, scp_r = solve_problem(sc, p)
        assert scp_a is not None and scp_r is not None and scp_r.success
        assert all("RICCATI" in h.solver_status for h in rel_r.history + scp_r.history)
        assert not any("RICCATI" in h.solver_status for h in rel_a.history + scp_a.history)
        assert (rel_r.iterations, scp_r.iterations) == (rel_a.iterations, scp_a.iterations)
        assert scp_r.cost == pytest.approx(scp_a.cost, rel=1e-6)
        assert scp_r.violation <= sc.scp.feas_tol  # (L1 optima need not be unique: states are not compared)


def test_fallback_when_the_kernel_does_not_converge(monkeypatch) -> None:
    _, spec, data = qp_subproblem("freeflyer", 2, Window(0, 100, 100), True, True, delta=0.3)
    monkeypatch.setattr(riccati_module, "MAX_ITER", 3)
    solver = RiccatiSolver(spec, fallback=lambda: PIQPSolver(spec))
    X, _, sol = solver.solve(data)
    assert X is not None and sol.ok
    assert sol.status.startswith("RICCATI_MAX_ITER") and sol.status.endswith("-> Status.PIQP_SOLVED")
    ref = PIQPSolver(spec).solve(data)[2]
    assert sol.objective == pytest.approx(ref.objective, rel=1e-9)


@pytest.mark.parametrize("name", ["freeflyer", "quadrotor"])
def test_mpc_windows_soft_terminal_cone_matches_clarabel(name) -> None:
    """An MPC window (H = 10, the paper's soft terminal term ‖W(x_H − x̄)‖₂) in the kernel, its one cone: the
    objective of the conic assembly solved by Clarabel and of the independent cvxpy model, for a target the window
    reaches (the term is 0: an exact penalty), one slightly off and one far off (the term is active); the returned
    trajectory keeps the trust region."""
    from ttompc.solvers.naive import NaiveCvxpySolver

    sc, spec, data = qp_subproblem(name, 5, Window(20, 10, 100), True, True, delta=0.3)
    spec = dataclasses.replace(spec, end_form="soft", tr_states=tuple(range(1, 11)))
    assert supports(spec)
    rng = np.random.default_rng(9)
    weights = np.linspace(1.0, 4.0, sc.state_dim)
    terms = []
    for scale in (0.0, 0.05, 0.5):
        target = data.X_ref[-1] + scale * rng.normal(size=sc.state_dim) * np.asarray(sc.state_scale)
        d = dataclasses.replace(data, terminal_target=target, terminal_weights=weights)
        X, _, sol = RiccatiSolver(spec).solve(d)
        assert sol.ok and sol.status.startswith("RICCATI_SOLVED ("), sol.status  # converged, not only close
        for other in (AssembledSolver(spec, ["clarabel"]), NaiveCvxpySolver(spec)):
            _, _, ref = other.solve(d)
            assert ref.ok and sol.objective == pytest.approx(ref.objective, rel=2e-6, abs=1e-7), type(other).__name__
        term = float(np.linalg.norm(weights * (X[-1] - target)))
        assert np.max(np.abs(X[1:] - d.X_ref[1:])) <= d.delta + 1e-7
        terms.append(term)
    assert terms[-1] > 1e-3  # the far target is not reached: the cone is active, not only its exact-penalty face


def _window_with_terminal_cost(name: str, seed: int) -> tuple[SubproblemSpec, SubproblemData, np.ndarray]:
    """(spec, data, state units) of an MPC window (H = 10, the soft terminal cone, a target slightly off) whose data
    carries a quadratic terminal cost-to-go model with a positive definite P, O(1) in the scaled variables."""
    sc, spec, data = qp_subproblem(name, 5, Window(20, 10, 100), True, True, delta=0.3)
    spec = dataclasses.replace(spec, end_form="soft", tr_states=tuple(range(1, 11)))
    n, (sx, _) = sc.state_dim, spec.units()
    rng = np.random.default_rng(seed)
    M = rng.normal(size=(n, n))
    model = QuadraticTerminalCost(
        hessian=(M @ M.T + 0.1 * np.eye(n)) / np.outer(sx, sx),
        gradient=rng.normal(size=n) / sx,
        center=data.X_ref[-1] + 0.1 * rng.normal(size=n) * sx,
    )
    target = data.X_ref[-1] + 0.05 * rng.normal(size=n) * sx
    data = dataclasses.replace(data, terminal_target=target, terminal_weights=np.linspace(1.0, 4.0, n))
    return spec, dataclasses.replace(data, terminal_cost=model), sx


@pytest.mark.parametrize("name", ["freeflyer", "quadrotor"])
def test_terminal_cost_model_through_the_stage_form(name) -> None:
    """``SubproblemData.terminal_cost`` (state units) becomes QN and q[N] in the scaled variables: the objective
    gains the model's value at any y, its constant included; without it the problem is the one before, array by
    array; RiccatiSolver's optimum is the independent cvxpy model's, with the window's cone and constraints."""
    spec, data, sx = _window_with_terminal_cost(name, 11)
    n, model = spec.n, data.terminal_cost
    assert model is not None
    st = StageQP(spec)
    qp, bare = st.build(data), dataclasses.replace(data, terminal_cost=None)
    qp0 = st.build(bare)
    assert qp0.cost.QN.shape == (0, 0) and qp0.cost.q is st.q  # no model: the arrays of the stage form without one
    rng = np.random.default_rng(12)
    for _ in range(3):
        y = rng.normal(size=(spec.H + 1, n + st.nu))
        e = y[-1, :n] * sx - model.center
        value = 0.5 * e @ model.hessian @ e + model.gradient @ e
        assert st.objective(y, qp, data) - st.objective(y, qp0, bare) == pytest.approx(value, rel=1e-9, abs=1e-9)
    X, _, sol = RiccatiSolver(spec).solve(data)
    assert sol.ok and sol.status.startswith("RICCATI_SOLVED ("), sol.status
    ref, Y = _cvxpy_solve(qp)
    const = 0.5 * model.center @ model.hessian @ model.center - model.gradient @ model.center
    assert sol.objective == pytest.approx(ref + const, rel=1e-6, abs=1e-7)
    np.testing.assert_allclose(X[-1] / sx, Y[-1, :n], atol=1e-5)  # x_H is unique (P definite); L1 controls need not be
    _, _, sol0 = RiccatiSolver(spec).solve(bare)
    assert abs(sol.objective - sol0.objective) > 1e-3  # the model moves the optimum


def test_fallback_for_a_terminal_cost_model(monkeypatch) -> None:
    """The conic solvers behind the kernel read ``SubproblemData.terminal_cost`` too: a kernel failure goes to them,
    and they reach the kernel's optimum."""
    spec, data, sx = _window_with_terminal_cost("freeflyer", 13)
    spec = dataclasses.replace(spec, terminal_value=True)
    X_ref, _, ref = RiccatiSolver(spec).solve(data)
    monkeypatch.setattr(riccati_module, "MAX_ITER", 3)
    X, _, sol = RiccatiSolver(spec, fallback=lambda: AssembledSolver(spec, ["clarabel"])).solve(data)
    assert sol.ok and sol.status.startswith("RICCATI_MAX_ITER") and sol.status.endswith("-> Solved"), sol.status
    assert X is not None and sol.objective == pytest.approx(ref.objective, rel=1e-6, abs=1e-7)
    np.testing.assert_allclose(X[-1] / sx, X_ref[-1] / sx, atol=1e-5)


def test_kernel_cache_is_keyed_on_all_its_sources() -> None:
    """numba keys a cached function on its own file, while the kernel's functions contain those of its other files:
    each carries the hash of all of them, so an edit to any recompiles the kernel."""
    from numba.core.registry import CPUDispatcher

    from ttompc.solvers.backends import riccati_cone, riccati_kernel, riccati_rows
    from ttompc.solvers.backends.riccati_jit import KERNEL, KERNEL_SOURCES

    modules = (riccati_cone, riccati_kernel, riccati_rows)
    assert {Path(m.__file__).name for m in modules if m.__file__} < set(KERNEL_SOURCES)
    dispatchers = [f for m in modules for f in vars(m).values() if isinstance(f, CPUDispatcher)]
    assert len(dispatchers) >= 30
    assert all(f._cache._cache_file._source_stamp == KERNEL.stamp for f in dispatchers)


def test_where_the_chain_takes_it() -> None:
    ff, rp = get_scenario("freeflyer"), get_scenario("rpod")
    assert backend_chain("auto", ff) == backend_chain("riccati", ff) == ["riccati", "piqp", "qoco", "clarabel"]
    assert backend_chain("piqp", ff) == ["piqp", "qoco", "clarabel"]  # the chain without the kernel
    assert backend_chain("auto", rp) == backend_chain("riccati", rp) == ["clarabel"]  # RPOD's subproblems have cones
    assert backend_chain("piqp", rp) == ["piqp", "clarabel"]  # PIQP takes no cone: Clarabel
    # the reference formulation (hard terminal equality) is not a stage-wise QP here: PIQP takes it
    _, spec, _ = qp_subproblem("freeflyer", 3, Window(0, 100, 100), True, False, delta=0.3)
    assert not supports(spec)
    assert isinstance(get_solver(spec, "auto", ff), PIQPSolver)
    p = ff.sample(np.random.default_rng(0))
    rel, scp = solve_problem(ff, p, backend="riccati", formulation="reference")
    assert scp is not None and scp.success and not any("RICCATI" in h.solver_status for h in scp.history)
    # an MPC window's soft terminal term is the kernel's one cone: the kernel takes the window, `piqp` the cone path
    w = Window(0, 10, 100)
    window = SCPProblem(ff, p, w, TerminalCost(rel.X[10], 1.0))
    res = solve_scp(window, rel.X[:11], rel.U[:10], SCPOptions(backend="auto"))
    assert res.success and all("RICCATI" in h.solver_status for h in res.history)
    res = solve_scp(window, rel.X[:11], rel.U[:10], SCPOptions(backend="piqp"))
    assert res.success and not any("RICCATI" in h.solver_status for h in res.history)


def test_solver_paths_reports_record() -> None:
    """``solver_path`` is what reports and datasets record: the name, the resolved chain (which tells the kernel's
    default from the PIQP path) and the trust-region norm."""
    from ttompc.solvers.backends import default_trust_norm, solver_path

    ff, rpod = get_scenario("freeflyer"), get_scenario("rpod")
    chain = ["riccati", "piqp", "qoco", "clarabel"]
    assert solver_path("auto", ff) == {"backend": "auto", "chain": chain, "trust_norm": "linf"}
    assert solver_path("piqp", ff) == {"backend": "piqp", "chain": chain[1:], "trust_norm": "linf"}
    assert solver_path("auto", rpod) == {"backend": "auto", "chain": ["clarabel"], "trust_norm": "l2"}
    assert default_trust_norm("clarabel", ff) == "linf" and default_trust_norm("conic", ff) == "l2"


def test_cli_solve_with_the_riccati_backend(tmp_path) -> None:
    """`ttompc solve --backend riccati` as a user runs it: the PIQP path's optimum."""
    import json

    from test_cli import ttompc

    res = ttompc("solve", "--scenario", "quadrotor", "--backend", "riccati", "--json", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    scp = json.loads(res.stdout)["results"]["SCP"]
    sc = get_scenario("quadrotor")
    _, ref = solve_problem(sc, sc.sample(np.random.default_rng(0)), backend="piqp")
    assert ref is not None and scp["status"] == "optimal" and scp["cost"] == pytest.approx(ref.cost, rel=1e-6)
