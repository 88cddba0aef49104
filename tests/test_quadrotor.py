"""Quadrotor physics (paper §V-A): the Euler step against the continuous drag ODE, the drag linearisation's
tangency (including v̄ = 0), sampling, constraint blocks and the REL/SCP solutions."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from ttompc.scenarios import InfeasibleProblemError, Problem, Window, get_scenario
from ttompc.scenarios.quadrotor import (
    DRAG,
    GOAL_REGION,
    MASS,
    N_STEPS,
    OBSTACLE_RADII,
    OBSTACLES,
    START_REGION,
    U_MAX,
    drag_jacobian,
)
from ttompc.solvers.scp import solve_problem


@pytest.fixture(scope="module")
def sc():
    return get_scenario("quadrotor")


def _problem(dt: float = 1.0) -> Problem:
    return Problem(
        x0=np.array([-1.9, 0.0, 0.4, 0, 0, 0]), goal=np.array([0.3, 0.0, 0.4, 0, 0, 0]), dt=dt, n_steps=N_STEPS
    )


def test_euler_step_matches_the_drag_ode_to_second_order(sc) -> None:
    """One Euler step vs solve_ivp of ṗ = v, v̇ = u/m − (c_d/m)‖v‖v with the force held over the step: the local
    error is O(dt²), so halving dt divides it by ~4."""
    x = np.array([0.1, -0.2, 0.3, 1.5, -0.8, 0.6])
    u = np.array([3.0, -2.0, 5.0])

    def ode(_t: float, y: np.ndarray) -> np.ndarray:
        v = y[3:]
        return np.concatenate([v, u / MASS - DRAG / MASS * np.linalg.norm(v) * v])

    errors = []
    for dt in (0.1, 0.05, 0.025):
        exact = solve_ivp(ode, (0.0, dt), x, method="DOP853", rtol=1e-12, atol=1e-12).y[:, -1]
        errors.append(np.linalg.norm(sc.step(_problem(dt), 0, x, u) - exact))
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    np.testing.assert_allclose(ratios, 4.0, rtol=0.05)
    assert errors[0] < 0.1**2  # constant of the O(dt²) term is below 1 for these speeds


@pytest.mark.parametrize("v_ref", [np.array([0.8, -0.3, 0.5]), np.zeros(3)])
def test_linearisation_is_tangent_to_the_step(sc, v_ref: np.ndarray) -> None:
    """The convex model reproduces the Euler step at the reference and its error is O(δ²) around it; at v̄ = 0 the
    drag is exactly quadratic, so the error is exactly dt·(c_d/m)‖δv‖δv."""
    problem = _problem()
    rng = np.random.default_rng(0)
    x_ref = np.concatenate([rng.normal(size=3), v_ref])
    u_ref = rng.normal(size=3)
    model = sc.convex_model(problem, Window(10, 1, N_STEPS), np.stack([x_ref, x_ref]), u_ref[None])
    A, B, c = model.A[0], model.B[0], model.c[0]
    np.testing.assert_allclose(A @ x_ref + B @ u_ref + c, sc.step(problem, 10, x_ref, u_ref), atol=1e-14)
    dx, du = rng.normal(size=6), rng.normal(size=3)
    errs = []
    for delta in (1e-1, 5e-2, 2.5e-2):
        x, u = x_ref + delta * dx, u_ref + delta * du
        errs.append(np.linalg.norm(sc.step(problem, 10, x, u) - (A @ x + B @ u + c)))
    np.testing.assert_allclose(np.array(errs[:-1]) / np.array(errs[1:]), 4.0, rtol=0.05)
    if not np.any(v_ref):
        dv = 2.5e-2 * dx[3:]
        assert errs[-1] == pytest.approx(problem.dt * DRAG / MASS * np.linalg.norm(dv) ** 2, rel=1e-9)
    # Jacobian against central finite differences of the drag
    h = 1e-6
    fd = np.stack(
        [
            (sc.step(problem, 0, x_ref + h * e, u_ref) - sc.step(problem, 0, x_ref - h * e, u_ref)) / (2 * h)
            for e in np.eye(6)
        ],
        axis=1,
    )
    np.testing.assert_allclose(fd, A, atol=1e-8)
    assert drag_jacobian(np.zeros(3)) == pytest.approx(np.zeros((3, 3)))


def test_sampling_regions_and_validation(sc) -> None:
    rng = np.random.default_rng(0)
    for _ in range(300):
        p = sc.sample(rng)
        sc.validate(p)
        for x, (lo, hi) in ((p.x0, START_REGION), (p.goal, GOAL_REGION)):
            assert np.all(x[:3] >= lo) and np.all(x[:3] <= hi) and not np.any(x[3:])
            assert np.all(np.linalg.norm(OBSTACLES - x[:3], axis=1) > OBSTACLE_RADII)
    for field in ("x0", "goal"):
        bad = {"x0": _problem().x0, "goal": _problem().goal}
        bad[field] = np.concatenate([OBSTACLES[3] + 0.05, np.zeros(3)])
        with pytest.raises(InfeasibleProblemError):
            sc.validate(Problem(dt=1.0, n_steps=N_STEPS, **bad))


def test_constraint_blocks(sc) -> None:
    problem = _problem()
    X, U = sc.initial_guess(problem)
    w = Window(30, 20, N_STEPS)
    blocks = {b.name: b for b in sc.constraints(problem, w, X[30:51], U[30:50], obstacles=True)}
    box, obs = blocks["control_box"], blocks["obstacles"]
    assert box.steps.tolist() == list(range(20)) and not box.soft and box.Gu.shape == (20, 3, 3)
    u = np.array([U_MAX, -U_MAX, 3.0])
    assert np.all(box.lower[0] - 1e-12 <= box.Gu[0] @ u) and np.all(box.Gu[0] @ u <= box.h[0] + 1e-12)
    assert np.any(box.Gu[0] @ (1.01 * u) > box.h[0]) and np.any(box.Gu[0] @ (1.01 * u) < box.lower[0])
    assert obs.steps.tolist() == list(range(1, 21)) and obs.obstacle and obs.soft and obs.Gx.shape == (20, 4, 6)
    assert [b.name for b in sc.constraints(problem, w, X[30:51], U[30:50], obstacles=False)] == ["control_box"]
    # violations count the zones containing each state (obstacle centres are inside exactly one)
    S = np.zeros((5, 6))
    S[:, :3] = [[-2.0, 0.0, 0.0], OBSTACLES[0], OBSTACLES[1], [0.5, 0.5, 0.6], OBSTACLES[3]]
    assert sc.violations(problem, S).tolist() == [0, 1, 1, 0, 1]
    assert sc.path_violation(problem, S, np.zeros((4, 3)), Window(0, 4, N_STEPS)) == pytest.approx(0.3)


def test_rel_and_scp_satisfy_the_nonlinear_problem(sc) -> None:
    problem = sc.sample(np.random.default_rng(11))
    rel, scp = solve_problem(sc, problem, backend="clarabel")
    assert rel.success and scp is not None and scp.success
    assert rel.cost <= scp.cost + 1e-6
    assert sc.violations(problem, rel.X).sum() > 0  # the obstacles matter for this problem
    for res in (rel, scp):
        # exact nonlinear dynamics: one-step defects within tolerance, and the controls replayed open loop in the
        # environment reproduce the plan (the defects compound, see Quadrotor.scp)
        X_next = np.stack([sc.step(problem, k, res.X[k], res.U[k]) for k in range(N_STEPS)])
        assert np.abs(X_next - res.X[1:]).max() <= sc.scp.feas_tol
        np.testing.assert_allclose(sc.rollout(problem, res.U), res.X, atol=1e-3)
        np.testing.assert_allclose(res.X[-1], problem.goal, atol=sc.scp.feas_tol)
        assert np.abs(res.U).max() <= U_MAX + 1e-6
    clearance = np.linalg.norm(scp.X[:, None, :3] - OBSTACLES[None], axis=-1) - OBSTACLE_RADII
    assert clearance.min() >= -1e-6
    assert sc.violations(problem, scp.X).sum() == 0
