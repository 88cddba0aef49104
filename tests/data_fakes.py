"""A tiny scenario and solver for data-pipeline tests: cheap closed-form "solves" with deterministic outputs
(including times), a non-identity model representation, problem features and designed failures.

Imported by spawned generation workers (its module registers the scenario), so it must stay importable alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np

from ttompc.scenarios import register
from ttompc.scenarios.base import (
    ConstraintBlock,
    ConvexModel,
    InfeasibleProblemError,
    MPCWeights,
    Problem,
    Scenario,
    SCPSettings,
    Window,
)
from ttompc.solvers.scp import SCPResult, SCPStatus

DT = 0.5
A_STEP = np.eye(6) + DT * np.eye(6, k=3)
B_IMP = np.vstack([np.zeros((3, 3)), np.eye(3)])
OBSTACLE, RADIUS = np.array([0.5, 0.5]), 0.2


@register
class FakeScenario(Scenario):
    name: ClassVar[str] = "data-fake"
    version: ClassVar[str] = "0.1"
    n_steps: ClassVar[int] = 12
    problem_params: ClassVar[tuple[str, ...]] = ("gain",)
    cost_norm = "l1"
    scp: ClassVar[SCPSettings] = SCPSettings(tr_start=1.0, tr_end=0.01)
    mpc: ClassVar[MPCWeights] = MPCWeights(fuel=1.0, end=10.0, target=1.0, dist=(1, 1, 1, 1, 1, 1))
    state_labels = ("x [m]", "y [m]", "ψ [rad]", "vx [m/s]", "vy [m/s]", "ω [rad/s]")
    control_labels = ("Δvx [m/s]", "Δvy [m/s]", "Δω [rad/s]")
    SCALE: ClassVar[np.ndarray] = np.array([2.0, 2.0, 1.0, 10.0, 10.0, 1.0])  # model representation = scaled

    def sample(self, rng: np.random.Generator) -> Problem:
        x0, goal = np.zeros(6), np.zeros(6)
        x0[:3], goal[:3] = rng.uniform(0, 1, 3), rng.uniform(0, 1, 3)
        return Problem(x0=x0, goal=goal, dt=DT, n_steps=self.n_steps, params={"gain": float(rng.uniform(1, 2))})

    def validate(self, problem: Problem) -> None:
        super().validate(problem)
        if problem.x0[2] > 0.97:  # a designed, rare "infeasible" problem
            raise InfeasibleProblemError("fake: heading too large")

    def step(self, problem: Problem, k: int, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return (x + u @ B_IMP.T) @ A_STEP.T

    def convex_model(self, problem: Problem, window: Window, X_ref: np.ndarray, U_ref: np.ndarray) -> ConvexModel:
        H = window.length
        return ConvexModel(
            np.broadcast_to(A_STEP, (H, 6, 6)), np.broadcast_to(A_STEP @ B_IMP, (H, 6, 3)), np.zeros((H, 6))
        )

    def constraints(
        self, problem: Problem, window: Window, X_ref: np.ndarray, U_ref: np.ndarray, *, obstacles: bool
    ) -> list[ConstraintBlock]:
        return []

    def violations(self, problem: Problem, X: np.ndarray, start: int = 0) -> np.ndarray:
        return (np.linalg.norm(np.asarray(X)[:, :2] - OBSTACLE, axis=1) < RADIUS).astype(int)

    def path_violation(
        self, problem: Problem, X: np.ndarray, U: np.ndarray, window: Window, *, obstacles: bool = True
    ) -> float:
        if not obstacles:
            return 0.0
        return float(np.max(RADIUS - np.linalg.norm(X[:, :2] - OBSTACLE, axis=1), initial=0.0))

    def to_model_states(self, problem: Problem, X: np.ndarray, start: int = 0) -> np.ndarray:
        return np.asarray(X, dtype=np.float64) * self.SCALE

    def from_model_states(self, problem: Problem, S: np.ndarray, start: int = 0) -> np.ndarray:
        return np.asarray(S, dtype=np.float64) / self.SCALE

    def batched_model(self, problems: Sequence[Problem], device: Any = "cpu") -> Any:
        raise NotImplementedError

    def problem_features(self, problem: Problem) -> dict[str, np.ndarray]:
        return {"gain": np.asarray(problem.params["gain"]), "obstacle": OBSTACLE.copy()}

    def problem_from_features(self, x0: np.ndarray, goal: np.ndarray, dt: float, features: dict[str, Any]) -> Problem:
        return Problem(x0=x0, goal=goal, dt=dt, n_steps=self.n_steps, params={"gain": float(features["gain"])})


def _result(scenario: Scenario, problem: Problem, U: np.ndarray, status: SCPStatus, iterations: int) -> SCPResult:
    X = scenario.rollout(problem, U)
    return SCPResult(
        status=status,
        X=X,
        U=U,
        cost=scenario.cost(U),
        violation=0.0,
        iterations=iterations,
        solve_time=0.01 * iterations,
        solver_time=0.005 * iterations,
        window=Window.full(problem),
    )


def fake_solve_problem(scenario: Scenario, problem: Problem, **kwargs: Any) -> tuple[SCPResult, SCPResult | None]:
    """Min-norm impulses reaching the goal (REL) and a problem-dependent detour (SCP); REL fails when
    x0[0] > 0.93, SCP when goal[1] < 0.08 (deterministic, so resumed runs match)."""
    N = scenario.n_steps
    G = np.zeros((6, 3 * N))  # x_N = A^N x0 + Σ A^(N−k) B u_k
    for k in range(N):
        G[:, 3 * k : 3 * k + 3] = np.linalg.matrix_power(A_STEP, N - k) @ B_IMP
    rhs = problem.goal - np.linalg.matrix_power(A_STEP, N) @ problem.x0
    U = np.linalg.lstsq(G, rhs, rcond=None)[0].reshape(N, 3)
    rel_status = SCPStatus.INFEASIBLE if problem.x0[0] > 0.93 else SCPStatus.OPTIMAL
    rel = _result(scenario, problem, U, rel_status, 3)
    if not rel.success:
        return rel, None
    detour = np.zeros_like(U)
    detour[: N // 2, 1], detour[N // 2 :, 1] = 0.01 * problem.params["gain"], -0.01 * problem.params["gain"]
    scp_status = SCPStatus.INFEASIBLE if problem.goal[1] < 0.08 else SCPStatus.OPTIMAL
    return rel, _result(scenario, problem, U + detour, scp_status, 5)


SOLVER = f"{__name__}:fake_solve_problem"
