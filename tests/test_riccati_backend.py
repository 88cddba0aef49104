"""The Riccati interior-point backend (first in the default chain, ``backend="auto"``): its kernel against a dense KKT
solve and Clarabel on small stage QPs, its stage-wise form against PIQP on the engine's subproblems, its terminal cone
(MPC windows) against Clarabel and cvxpy, whole REL + SCP solves against the PIQP path (``backend="piqp"``), the
fallback, and where the chain takes it."""

from __future__ import annotations

import cvxpy as cp
import numpy as np
import pytest
from helpers import qp_subproblem, waypoint_subproblem

from ttompc.scenarios import Window, get_scenario
from ttompc.solvers import SCPOptions, SCPProblem, TerminalCost, solve_problem, solve_scp
from ttompc.solvers.backends import backend_chain, get_solver
from ttompc.solvers.backends import riccati as riccati_module
from ttompc.solvers.backends.qp import PIQPSolver
from ttompc.solvers.backends.riccati import RiccatiSolver, supports


def _random_stage_qp(seed: int, N: int = 6, n: int = 3, nu: int = 2):
    rng = np.random.default_rng(seed)
    A = np.eye(n) + 0.1 * rng.normal(size=(N, n, n))
    B = rng.normal(size=(N, n, nu))
    c = 0.1 * rng.normal(size=(N, n))
    Qd = rng.uniform(0.5, 2.0, size=(N + 1, n + nu))
    q = rng.normal(size=(N + 1, n + nu))
    return A, B, c, rng.normal(size=n), Qd, q


def _kernel(args, boxes, rows, n, nu):
    from ttompc.solvers.backends.riccati_kernel import solve

    A, B, c, x0, Qd, q = args
    N = A.shape[0]
    y, pi = np.zeros((N + 1, n + nu)), np.zeros((N, n))
    full = (A, B, c, x0, Qd, q, *boxes, *rows, np.zeros(0), np.zeros(0), y, pi, 1e-10, 1e-11, 100, n, nu)
    code = solve(*full)[0]
    return code, y


def _no_rows(width: int = 1):
    return np.zeros(0, np.int64), np.zeros((0, width), np.int64), np.zeros((0, width)), np.zeros(0), np.zeros(0)


def test_kernel_without_constraints_is_the_kkt_solution() -> None:
    """No inequalities: one Newton step; the dense KKT system of the equality-constrained QP gives the same y."""
    n, nu, N = 3, 2, 6
    args = _random_stage_qp(0, N, n, nu)
    A, B, c, x0, Qd, q = args
    boxes = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0))
    code, y = _kernel(args, boxes, _no_rows(), n, nu)
    assert code == 0
    # dense KKT over z = [y_0 .. y_N] (the last stage's u is the kernel's dummy: fixed to 0 here too)
    ny, nz = n + nu, (N + 1) * (n + nu)
    H, g = np.diag(Qd.ravel()), q.ravel().copy()
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
    args = _random_stage_qp(1, N, n, nu)
    A, B, c, x0, Qd, q = args
    rng = np.random.default_rng(2)
    ks = np.repeat(np.arange(1, N + 1), 2)
    bk = np.concatenate([ks, np.arange(N), np.arange(N)])
    bj = np.concatenate([np.zeros(2 * N, np.int64), np.full(N, n), np.full(N, n)])
    bs = np.concatenate([np.tile([1.0, -1.0], N), np.ones(N), -np.ones(N)])
    bd = np.concatenate([np.full(2 * N, 0.4), np.zeros(2 * N)])
    brho = np.concatenate([np.zeros(2 * N), np.full(2 * N, 0.7)])  # hard |x[0]| ≤ 0.4, then 0.7·|u[0]|
    rk = np.arange(1, N)
    ri = np.tile([1, 2], (N - 1, 1))
    rg = rng.normal(size=(N - 1, 2))
    rd = rng.uniform(-0.2, 0.2, size=N - 1)
    rrho = np.full(N - 1, 3.0)
    code, y = _kernel(args, (bk, bj, bs, bd, brho), (rk, ri, rg, rd, rrho), n, nu)
    assert code == 0
    Y = cp.Variable((N + 1, n + nu))
    cons = [Y[0, :n] == x0, Y[N, n:] == 0]
    cons += [Y[k + 1, :n] == A[k] @ Y[k, :n] + B[k] @ Y[k, n:] + c[k] for k in range(N)]
    cons += [bs[i] * Y[bk[i], bj[i]] <= bd[i] for i in range(len(bk)) if brho[i] == 0]
    soft = sum(brho[i] * cp.pos(bs[i] * Y[bk[i], bj[i]] - bd[i]) for i in range(len(bk)) if brho[i] > 0)
    soft += sum(rrho[i] * cp.pos(rg[i] @ Y[rk[i], ri[i]] - rd[i]) for i in range(len(rk)))
    obj = 0.5 * cp.sum(cp.multiply(Qd, cp.square(Y))) + cp.sum(cp.multiply(q, Y)) + soft
    cp.Problem(cp.Minimize(obj), cons).solve(solver=cp.CLARABEL)
    np.testing.assert_allclose(y, Y.value, atol=1e-5)
    assert np.max(np.abs(y[1:, 0])) <= 0.4 + 1e-9  # the hard boxes hold
    assert np.isclose(np.max(np.abs(y[1:, 0])), 0.4)  # and one of them is active


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
    import dataclasses

    from ttompc.solvers.backends.conic import AssembledSolver
    from ttompc.solvers.naive import NaiveCvxpySolver

    sc, spec, data = qp_subproblem(name, 5, Window(20, 10, 100), True, True, delta=0.3)
    spec = dataclasses.replace(spec, terminal="soft", tr_states=tuple(range(1, 11)))
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
