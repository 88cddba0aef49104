"""A terminal cost-to-go model in the conic windows (``mpc.terminal=value`` / ``value+target`` on RPOD, or any window
sent to QOCO/Clarabel): its dense block in P and its linear term in q (``ttompc.solvers.objective``) against an
independent cvxpy model and the riccati kernel on the same subproblem, Clarabel's in-place update of both, whole
windows through the engine against a brute-force solve, and a zero model against the target-only window."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import cvxpy as cp
import numpy as np
import pytest
from helpers import qp_subproblem

from ttompc.scenarios import Window, get_scenario
from ttompc.scenarios.base import BlockKind, Problem, Scenario
from ttompc.solvers import SCPOptions, SCPProblem, SCPResult, SCPStatus, TerminalCost, solve_problem, solve_scp
from ttompc.solvers.backends.conic import AssembledSolver
from ttompc.solvers.backends.riccati import RiccatiSolver
from ttompc.solvers.naive import NaiveCvxpySolver
from ttompc.solvers.spec import QuadraticTerminalCost, SubproblemData, SubproblemSpec


class Expansion(NamedTuple):
    value: float
    gradient: np.ndarray
    hessian: np.ndarray


class QuadraticValue:
    """J(x) = gᵀ(x − c) + ½(x − c)ᵀM(x − c): a ``TerminalValue`` whose local model is itself (exact at every
    reference)."""

    def __init__(self, center: np.ndarray, gradient: np.ndarray, hessian: np.ndarray) -> None:
        self.center, self.g, self.M = center, gradient, hessian

    def expand(self, x: np.ndarray) -> Expansion:
        d = np.asarray(x) - self.center
        return Expansion(float(self.g @ d + 0.5 * d @ self.M @ d), self.g + self.M @ d, self.M)

    def __call__(self, x: np.ndarray) -> float:
        return self.expand(x).value


def _psd(rng: np.random.Generator, units: np.ndarray, size: float) -> np.ndarray:
    """A positive definite matrix of about ``size`` in the scaled state x / units."""
    n = len(units)
    R = rng.normal(size=(n, n)) / np.sqrt(n)
    return size * (R @ R.T + 0.1 * np.eye(n)) / np.outer(units, units)


def _model(rng: np.random.Generator, center: np.ndarray, units: np.ndarray, size: float) -> QuadraticTerminalCost:
    return QuadraticTerminalCost(
        _psd(rng, units, size),
        size * rng.normal(size=len(units)) / units,
        center + 0.1 * rng.normal(size=len(units)) * units,
    )


def _window(name: str, terminal: str, seed: int) -> tuple[SubproblemSpec, SubproblemData, np.ndarray]:
    """(spec, data, state units) of an H = 10 window subproblem with a terminal model (and the target's cone for
    ``end_form="soft"``)."""
    sc, spec, data = qp_subproblem(name, 5, Window(20, 10, 100), True, True, delta=0.3)
    spec = dataclasses.replace(spec, end_form=terminal, tr_states=tuple(range(1, 11)), terminal_value=True)
    sx, rng = sc.state_units(), np.random.default_rng(seed)
    size = 1e-3 if name == "rpod" else 1.0  # RPOD's fuel is in m/s, its costates ~1e-3 per metre
    data = dataclasses.replace(data, terminal_cost=_model(rng, data.X_ref[-1], sx, size))
    if terminal == "soft":
        target = data.X_ref[-1] + 0.05 * rng.normal(size=len(sx)) * sx
        data = dataclasses.replace(data, terminal_target=target, terminal_weights=size * np.linspace(1.0, 4.0, len(sx)))
    return spec, data, sx


@pytest.mark.parametrize("terminal", ["value", "soft"])
@pytest.mark.parametrize("name", ["rpod", "quadrotor", "freeflyer"])
def test_the_terminal_model_in_the_conic_assembly(name: str, terminal: str) -> None:
    """QOCO and Clarabel on the assembly reach the optimum of the independent cvxpy model (objective with the model's
    constant, and x_H, unique where P is definite), and of the riccati kernel where it takes the window."""
    spec, data, sx = _window(name, terminal, 11)
    refs = [NaiveCvxpySolver(spec).solve(data)]
    if name != "rpod":
        refs.append(RiccatiSolver(spec).solve(data))
    for X_ref, _, ref in refs:
        assert ref.ok and X_ref is not None, ref.status
        for backend in ("clarabel", "qoco"):
            X, _, sol = AssembledSolver(spec, [backend]).solve(data)
            assert sol.ok and X is not None, sol.status
            assert sol.objective == pytest.approx(ref.objective, rel=2e-6, abs=1e-7 * abs(ref.objective) + 1e-9)
            np.testing.assert_allclose(X[-1] / sx, X_ref[-1] / sx, atol=5e-5)


def test_clarabel_updates_the_model_in_place() -> None:
    """A persistent Clarabel solver given a second model (new block values, new linear term) reaches what a fresh
    solver reaches; the model moves the optimum."""
    spec, data, sx = _window("quadrotor", "soft", 12)
    other = dataclasses.replace(data, terminal_cost=_model(np.random.default_rng(13), data.X_ref[-1], sx, 1.0))
    solver = AssembledSolver(spec, ["clarabel"])
    X1, _, _ = solver.solve(data)
    X2, _, sol = solver.solve(other)
    X_fresh, _, fresh = AssembledSolver(spec, ["clarabel"]).solve(other)
    assert sol.ok and X1 is not None and X2 is not None and X_fresh is not None
    assert sol.objective == pytest.approx(fresh.objective, rel=1e-6)
    np.testing.assert_allclose(X2[-1] / sx, X_fresh[-1] / sx, atol=5e-5)  # the first data's equilibration
    assert np.abs(X1[-1] - X2[-1]).max() > 1e-3 * sx.min()


def test_a_model_without_its_block_is_refused() -> None:
    """A spec assembled without the block would drop a model without a word: refused; so is 'value' without it."""
    spec, data, _ = _window("quadrotor", "soft", 14)
    with pytest.raises(ValueError, match="terminal_value=True"):
        AssembledSolver(dataclasses.replace(spec, terminal_value=False), ["clarabel"]).solve(data)
    with pytest.raises(ValueError, match="terminal_value=True"):
        AssembledSolver(dataclasses.replace(spec, end_form="value", terminal_value=False), ["clarabel"])


@pytest.fixture(scope="module")
def rpod() -> tuple[Scenario, Problem, SCPResult]:
    sc = get_scenario("rpod")
    p = sc.sample(np.random.default_rng(2))
    _, full = solve_problem(sc, p)
    assert full is not None and full.success and full.costates is not None
    return sc, p, full


def _brute_force(sc: Scenario, p: Problem, window: Window, x0: np.ndarray, value: QuadraticValue, w: float) -> float:
    """min w·(Σ‖u‖₂ + J(x_H)) over a convex RPOD window (dynamics and approach cone, no keep-out zone and no trust
    region from the waypoint on), modelled in cvxpy from the scenario's own matrices."""
    H, n, m = window.length, sc.state_dim, sc.control_dim
    X, U = cp.Variable((H + 1, n)), cp.Variable((H, m))
    guess = np.zeros((H + 1, n)), np.zeros((H, m))
    lin = sc.convex_model(p, window, *guess)
    cons = [X[0] == x0] + [X[j + 1] == lin.A[j] @ X[j] + lin.B[j] @ U[j] + lin.c[j] for j in range(H)]
    for b in sc.constraints(p, window, *guess, obstacles=True):
        assert b.Gu is None and b.kind is not BlockKind.INEQ  # the keep-out zone ends before the waypoint
        for kk, j in enumerate(b.steps):
            e = b.Gx[kk] @ X[j] - b.h[kk]
            cons.append(e == 0 if b.kind is BlockKind.EQ else cp.norm(e[1:]) <= e[0])
    d = X[H] - value.center
    J = value.g @ d + 0.5 * cp.quad_form(d, cp.psd_wrap(value.M))
    prob = cp.Problem(cp.Minimize(w * (cp.sum(cp.norm(U, axis=1)) + J)), cons)
    prob.solve(solver="CLARABEL")
    assert prob.status == cp.OPTIMAL
    return float(prob.value)


@pytest.mark.parametrize("soft", [False, True])
@pytest.mark.parametrize("backend", ["auto", "qoco"])
def test_rpod_window_with_a_value_is_the_brute_force_optimum(rpod, backend: str, soft: bool) -> None:
    """An RPOD window [90, 97) from a state off the optimum whose end pays a quadratic value about the optimum (its
    costate as the slope): the engine (Clarabel, RPOD's path; QOCO) reaches the cvxpy optimum of the same window, its
    merit reading J; in soft mode the value, a cost-to-go, is weighted as the stage cost (``mpc.fuel``)."""
    sc, p, full = rpod
    window, sx = Window(90, 7, p.n_steps), sc.state_units()
    end = window.stop
    value = QuadraticValue(full.X[end], full.costates[end], _psd(np.random.default_rng(3), sx, 0.1))
    x0 = full.X[window.start] + 0.05 * sx * np.random.default_rng(4).normal(size=sc.state_dim)
    X0 = full.X[window.start : end + 1].copy()
    X0[0] = x0
    scp = SCPProblem(sc, p, window, TerminalCost(full.X[end], 0.0, value=value), soft=soft)
    res = solve_scp(scp, X0, full.U[window.start : end], SCPOptions(backend=backend))
    assert res.success and res.costates is not None, res
    w = sc.mpc.fuel if soft else 1.0
    merit = w * (res.cost + value(res.X[-1]))
    assert merit == pytest.approx(_brute_force(sc, p, window, x0, value, w), rel=1e-5)
    assert res.history[res.best_iteration].objective == pytest.approx(merit, rel=1e-9)


def test_quadrotor_window_forced_to_the_conic_backends_is_the_riccati_windows() -> None:
    """A quadrotor window with ``value+target`` solved by SCP on the riccati kernel (``auto``) and on QOCO and
    Clarabel: the same iterate, to the stopping rule's tolerance."""
    sc = get_scenario("quadrotor")
    p = sc.sample(np.random.default_rng(3))
    _, full = solve_problem(sc, p)
    assert full is not None and full.costates is not None
    window, sx = Window(20, 10, p.n_steps), sc.state_units()
    value = QuadraticValue(full.X[30], full.costates[30], _psd(np.random.default_rng(5), sx, 10.0))
    target = full.X[30] + 0.1 * sx
    scp = SCPProblem(sc, p, window, TerminalCost(target, sc.mpc.tracking, value=value), soft=True)
    X0 = full.X[20:31] + 0.05 * sx * np.random.default_rng(6).normal(size=(11, sc.state_dim))
    X0[0] = full.X[20]
    runs = {b: solve_scp(scp, X0, full.U[20:30], SCPOptions(backend=b)) for b in ("auto", "clarabel", "qoco")}
    ref = runs.pop("auto")
    assert ref.success and ref.history[0].solver_status.startswith("RICCATI_SOLVED")
    for backend, res in runs.items():
        assert res.success, backend
        merit, ref_merit = (r.history[r.best_iteration].objective for r in (res, ref))
        assert merit == pytest.approx(ref_merit, rel=1e-5), backend
        np.testing.assert_allclose(res.X / sx, ref.X / sx, atol=2e-3, err_msg=backend)


def test_a_zero_value_beside_the_target_is_the_target_only_window(rpod) -> None:
    """``value+target`` with a value of zero slope and curvature (its block allocated, its values 0) gives the
    target-only window's solution, on Clarabel (RPOD's path) and QOCO."""
    sc, p, full = rpod
    window, n, sx = Window(60, 10, p.n_steps), sc.state_dim, sc.state_units()
    target = full.X[70] + 0.5 * sx
    zero = QuadraticValue(target, np.zeros(n), np.zeros((n, n)))
    X0, U0 = full.X[60:71], full.U[60:70]
    for backend in ("auto", "qoco"):
        options = SCPOptions(backend=backend)
        only = solve_scp(SCPProblem(sc, p, window, TerminalCost(target, 0.1), soft=True), X0, U0, options)
        both = solve_scp(SCPProblem(sc, p, window, TerminalCost(target, 0.1, zero), soft=True), X0, U0, options)
        assert only.status is both.status is SCPStatus.OPTIMAL, backend
        merits = [r.history[r.best_iteration].objective for r in (only, both)]
        assert merits[1] == pytest.approx(merits[0], rel=2e-6), backend
        np.testing.assert_allclose(both.X / sx, only.X / sx, atol=1e-4, err_msg=backend)
