"""Costates from the conic backends (QOCO, Clarabel): the multipliers of the assembled subproblem's dynamics rows
are ∂J*/∂x_k per unit of the state, the riccati kernel's convention. On RPOD windows (the only scenario whose windows
go to the conic backends by default) against finite differences of the optimal cost-to-go, and on the free-flyer's
and the quadrotor's subproblems against the riccati kernel on the same data."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import qp_subproblem

from ttompc.scenarios import Window, get_scenario
from ttompc.scenarios.base import Problem, Scenario
from ttompc.solvers import SCPOptions, SCPProblem, SCPResult, solve_problem, solve_scp
from ttompc.solvers.backends.conic import AssembledSolver
from ttompc.solvers.backends.riccati import RiccatiSolver

BACKENDS = ["clarabel", "qoco"]


@pytest.fixture(scope="module")
def rpod() -> tuple[Scenario, Problem, SCPResult, dict[int, tuple[np.ndarray, np.ndarray]]]:
    """RPOD's problem, its optimum and the one-sided differences of its cost-to-go at the steps tested."""
    sc = get_scenario("rpod")
    p = sc.sample(np.random.default_rng(0))
    _, full = solve_problem(sc, p)
    assert full is not None and full.success
    return sc, p, full, {k: _differences(sc, p, full, k) for k in (10, 30, 94)}


def _differences(sc: Scenario, p: Problem, full: SCPResult, k: int) -> tuple[np.ndarray, np.ndarray]:
    """One-sided differences (forward, backward) of the optimal cost-to-go J*(x, k), re-solved (the default path,
    Clarabel) from the optimum with x_k moved by ±1e-3 of each state unit."""
    N, options = p.n_steps, SCPOptions()

    def cost_to_go(x: np.ndarray) -> float:
        X0 = full.X[k:].copy()
        X0[0] = x
        return sc.cost(solve_scp(SCPProblem(sc, p, Window(k, N - k, N)), X0, full.U[k:], options).U)

    J, steps = cost_to_go(full.X[k]), 1e-3 * sc.state_units()
    fwd = np.array([(cost_to_go(full.X[k] + h * e) - J) / h for e, h in zip(np.eye(sc.state_dim), steps, strict=True)])
    bwd = np.array([(J - cost_to_go(full.X[k] - h * e)) / h for e, h in zip(np.eye(sc.state_dim), steps, strict=True)])
    return fwd, bwd


def _costate(sc: Scenario, p: Problem, full: SCPResult, k: int, backend: str) -> np.ndarray:
    """λ_k of the window [k − 1, N) solved from the optimum (its x_k is a variable): ``SCPResult.costates[1]``."""
    N = p.n_steps
    window = SCPProblem(sc, p, Window(k - 1, N - k + 1, N))
    res = solve_scp(window, full.X[k - 1 :], full.U[k - 1 :], SCPOptions(backend=backend))
    assert res.success and res.costates is not None and res.costates.shape == (N - k + 2, sc.state_dim)
    assert np.isnan(res.costates[0]).all() and np.isfinite(res.costates[1:]).all()
    return res.costates[1]


def test_rpod_expert_solves_carry_costates(rpod) -> None:
    """The default path (Clarabel) gives RPOD's open-loop optimum its costates, as data generation stores them."""
    sc, _, full, _ = rpod
    assert full.costates is not None and full.costates.shape == (sc.n_steps + 1, sc.state_dim)
    assert np.isnan(full.costates[0]).all() and np.isfinite(full.costates[1:]).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_rpod_costates_are_the_gradient_of_the_optimal_cost_to_go(rpod, backend: str) -> None:
    """Where J* is smooth (one-sided differences agree) λ_k is its gradient: central differences, at two steps."""
    sc, p, full, differences = rpod
    for k in (10, 30):
        fwd, bwd = differences[k]
        scale = np.abs(fwd).max()
        assert np.abs(fwd - bwd).max() < 0.01 * scale  # smooth here, to the differences' accuracy
        np.testing.assert_allclose(_costate(sc, p, full, k, backend), (fwd + bwd) / 2, atol=2e-3 * scale)


@pytest.mark.parametrize("backend", BACKENDS)
def test_rpod_costates_are_a_subgradient_where_the_cost_to_go_has_a_kink(rpod, backend: str) -> None:
    """After the waypoint RPOD's window is convex and its 2-norm fuel cost-to-go has kinks (the one-sided differences
    disagree): λ_k is a subgradient, between the backward and the forward difference of every component."""
    sc, p, full, differences = rpod
    k = 94
    fwd, bwd = differences[k]
    tol = 1e-3 * np.abs(fwd).max()
    assert np.abs(fwd - bwd).max() > 0.1 * np.abs(fwd).max()  # a kink: no gradient to compare with
    lam = _costate(sc, p, full, k, backend)
    assert np.all(bwd - tol <= lam) and np.all(lam <= fwd + tol)


@pytest.mark.parametrize("name", ["quadrotor", "freeflyer"])
@pytest.mark.parametrize("delta", [0.3, 10.0])
def test_conic_costates_are_the_riccati_kernels(name: str, delta: float) -> None:
    """The same subproblem (an active and an inactive trust region) to the kernel and to each conic solver: the same
    multipliers, though the kernel works in the scaled variables x / state_scale and the conic solvers on rows in
    the state's units."""
    _, spec, data = qp_subproblem(name, 4, Window(20, 10, 100), True, True, delta=delta)
    _, _, ref = RiccatiSolver(spec).solve(data)
    assert ref.ok and ref.costates is not None
    for backend in BACKENDS:
        _, _, sol = AssembledSolver(spec, [backend]).solve(data)
        assert sol.ok and sol.costates is not None, sol.status
        np.testing.assert_allclose(sol.costates, ref.costates, atol=2e-5 * np.abs(ref.costates).max())
