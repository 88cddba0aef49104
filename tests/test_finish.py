"""The finish cost (``ttompc.mpc.finish``) against brute-force finishes, and its cone in the SCP subproblem."""

from __future__ import annotations

import cvxpy as cp
import numpy as np
import pytest

from ttompc.mpc import MPCSettings
from ttompc.mpc.finish import finish_cost, min_tail
from ttompc.scenarios import get_scenario
from ttompc.scenarios.base import Problem, Scenario, Window
from ttompc.solvers.results import TerminalCost
from ttompc.solvers.scp import SCPOptions, SCPProblem, solve_rel, solve_scp


def least_finish(sc: Scenario, p: Problem, window: Window, x: np.ndarray, ref: np.ndarray | None = None) -> float:
    """Brute force: the least stage cost that reaches the goal exactly from ``x`` after ``window`` on the same
    linearised dynamics (along the straight line from ``ref``, default ``x``), no keep-out zones, by a generic cone
    solver."""
    N = p.n_steps
    tail = Window(window.stop, N - window.stop, N)
    X_ref, U_ref = sc.initial_guess(p, tail, x if ref is None else ref)
    model = sc.convex_model(p, tail, X_ref, U_ref)
    T = tail.length
    X, U = cp.Variable((T + 1, sc.state_dim)), cp.Variable((T, sc.control_dim))
    cons = [X[0] == x, X[T] == p.goal]
    cons += [X[k + 1] == model.A[k] @ X[k] + model.B[k] @ U[k] + model.c[k] for k in range(T)]
    if sc.cost_norm == "quad":
        cost = 0.5 * cp.sum_squares(U)
    elif sc.cost_norm == "l1":
        cost = cp.sum(cp.abs(U))
    else:
        cost = sum(cp.norm(U[k], 2) for k in range(T))
    prob = cp.Problem(cp.Minimize(cost), cons)
    prob.solve(solver="CLARABEL")
    assert prob.status == "optimal", prob.status
    return float(prob.value)


def _problem(name: str, seed: int = 1) -> tuple[Scenario, Problem]:
    sc = get_scenario(name)
    return sc, sc.sample(np.random.default_rng(seed))


@pytest.mark.parametrize("left", [5, 20, 80])
def test_quadratic_finish_is_the_least_energy_finish(left: int) -> None:
    """Quadratic stage cost: the closed form (Gramian) is the optimal unconstrained finish, from any state; so at
    another state than the warm start's too."""
    sc, p = _problem("quadrotor")
    N = p.n_steps
    window = Window(N - left - 10, 10, N)
    price = finish_cost(sc, p, window, p.x0, weight=1.0)
    assert price is not None and price.squared
    for x in (p.x0, p.x0 + 0.05 * np.arange(6)):
        assert price(x) == pytest.approx(least_finish(sc, p, window, x, ref=p.x0), rel=1e-4)
    double = finish_cost(sc, p, window, p.x0, weight=2.0)
    assert double is not None and double(p.x0) == pytest.approx(2 * price(p.x0))


@pytest.mark.parametrize("name", ["freeflyer", "rpod"])
def test_norm_finish_is_a_feasible_finish_fuel_at_the_warm_start(name: str) -> None:
    """Norm stage costs: at the warm start's state the price is the fuel of the least-energy finish, a feasible
    finish, so no less than the least fuel and (measured) within 1.5x of it; elsewhere it scales as a norm."""
    sc, p = _problem(name)
    N = p.n_steps
    for left in (3, 10, 30, 80):
        window = Window(N - left - 10, 10, N)
        price = finish_cost(sc, p, window, p.x0, weight=1.0)
        assert price is not None and not price.squared
        best = least_finish(sc, p, window, p.x0)
        assert 0.995 * best <= price(p.x0) <= 1.6 * best, (left, price(p.x0), best)  # 0.995: the ridge
    # positively homogeneous in the offset from the state that needs no control (l = L x_free)
    x_free = np.linalg.lstsq(price.L, price.l, rcond=None)[0]
    assert price(x_free) == pytest.approx(0.0, abs=1e-9)
    assert price(x_free + 2 * (p.x0 - x_free)) == pytest.approx(2 * price(p.x0), rel=1e-9)


def test_short_tails_and_end_windows_get_no_finish() -> None:
    sc, p = _problem("quadrotor")
    N = p.n_steps
    assert min_tail(sc) == 3
    assert finish_cost(sc, p, Window(N - 12, 10, N), p.x0, 1.0) is None  # 2 steps left
    assert finish_cost(sc, p, Window(N - 13, 10, N), p.x0, 1.0) is not None
    with pytest.raises(ValueError, match="reaches the end"):
        finish_cost(sc, p, Window(N - 10, 10, N), p.x0, 1.0)


@pytest.mark.parametrize("name", ["quadrotor", "freeflyer"])
def test_window_with_finish_solves_as_the_modelling_layer_does(name: str) -> None:
    """The finish cone of the assembled subproblem (QOCO/Clarabel) poses what cvxpy poses from the same data: the
    same window optimum; the term changes that optimum, and the solved window pays less for finishing."""
    sc, p = _problem(name, seed=3)
    N = p.n_steps
    window = Window(40, 10, N)
    rel = solve_rel(sc, p)
    X0, U0 = rel.X[40:51].copy(), rel.U[40:50].copy()
    price = finish_cost(sc, p, window, X0[-1], weight=sc.mpc.fuel)
    assert price is not None
    target = X0[-1] + 0.1 * sc.state_units()  # a target off the relaxed path: the two terms pull apart
    plain = TerminalCost(target, sc.mpc.tracking)
    priced = TerminalCost(target, sc.mpc.tracking, price)
    soft = SCPProblem(sc, p, window, priced, soft=True)
    fast = solve_scp(soft, X0, U0)
    naive = solve_scp(soft, X0, U0, SCPOptions(backend="cvxpy-naive"))
    without = solve_scp(soft.update(terminal=plain), X0, U0)
    assert fast.success and naive.success and without.success
    merit = lambda r: sc.mpc.fuel * sc.cost(r.U) + priced(r.X[-1])  # noqa: E731
    assert merit(fast) == pytest.approx(merit(naive), rel=1e-3, abs=1e-6)
    assert price(fast.X[-1]) < price(without.X[-1])
    assert priced(fast.X[-1]) == pytest.approx(plain(fast.X[-1]) + price(fast.X[-1]))


def test_finish_setting_is_validated() -> None:
    assert MPCSettings().finish == 0.0  # the paper's: no finish cost
    with pytest.raises(ValueError, match="finish must be >= 0"):
        MPCSettings(finish=-1.0)
