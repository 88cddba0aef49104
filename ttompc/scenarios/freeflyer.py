"""Free-flyer testbed (paper §V-A, Fig. 3): a planar air-bearing robot with four thruster clusters crossing a granite
table with four circular obstacles.

State x = [x, y, ψ, ẋ, ẏ, ψ̇] (m, rad, m/s, rad/s); control a = [Δv_x, Δv_y, a_ψ] is an impulse in the global
frame with Δψ̇ = (m/J)·a_ψ. Dynamics are the impulsive double integrator x_{k+1} = A (x_k + B a_k). The per-thruster
bound |Λ⁻¹ R_BG(ψ) a| ≤ Δv_max is non-convex through the heading, so it is linearised in (ψ, a) every iteration
and REL is itself an SCP (obstacles off, bound on).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np

from ttompc.scenarios import register
from ttompc.scenarios.base import (
    BlockKind,
    ConstraintBlock,
    ConvexModel,
    InfeasibleProblemError,
    MPCWeights,
    Problem,
    SCPSettings,
    Window,
)
from ttompc.scenarios.dynamics import CompiledBatchedModel, CompiledScenario, CompiledStep
from ttompc.scenarios.keepout import keepout_block, keepout_distance

MASS = 16.0  # kg
INERTIA = 0.18  # kg m²
ROBOT_RADIUS = 0.15  # m
F_MAX = 0.2  # N per thruster cluster
LEVER = 0.11461  # m
DT = 0.4  # s
N_STEPS = 100
DV_MAX = F_MAX * DT / MASS  # 0.005 m/s per thruster per step
TABLE = (np.array([0.15, 0.15]), np.array([3.35, 2.35]))  # position box (table shrunk by the robot radius)
START_REGION = (np.array([0.15, 0.15]), np.array([0.35, 2.35]))
GOAL_REGION = (np.array([3.15, 0.15]), np.array([3.35, 2.35]))
OBSTACLES = np.array([[1.0, 0.7], [1.5, 1.7], [2.5, 0.75], [2.5, 1.75]])
OBSTACLE_RADIUS = 0.2
SAFETY_MARGIN = 1.1
R_EFF = (OBSTACLE_RADIUS + ROBOT_RADIUS) * SAFETY_MARGIN  # 0.385 m, used in OCP, MPC, ctg and rollouts
VIOLATION_TOL = 1e-5  # m; an SCP solution touching an obstacle boundary is not a violation

# Thruster allocation pseudo-inverse Λ⁻¹ (4×3): body (F_x, F_y, τ) -> cluster Δv.
LAMBDA_INV = np.array(
    [
        [0.0, 0.5, 1 / (4 * LEVER)],
        [0.5, 0.0, -1 / (4 * LEVER)],
        [0.0, 0.5, -1 / (4 * LEVER)],
        [0.5, 0.0, 1 / (4 * LEVER)],
    ]
)
A_STEP = np.eye(6) + DT * np.block([[np.zeros((3, 3)), np.eye(3)], [np.zeros((3, 6))]])
B_IMP = np.vstack([np.zeros((3, 3)), np.diag([1.0, 1.0, MASS / INERTIA])])


def thruster_dv(psi: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Per-cluster Δv Λ⁻¹ R_BG(ψ) a for headings (...,) and global impulses (..., 3): (..., 4)."""
    c, s = np.cos(psi), np.sin(psi)
    body = np.stack([c * a[..., 0] + s * a[..., 1], -s * a[..., 0] + c * a[..., 1], a[..., 2]], axis=-1)
    return body @ LAMBDA_INV.T


def _step(x: Any, u: Any, k: int, p: Any, out: Any) -> None:
    """x_{k+1} = A (x + B u), p = [dt]: the impulse changes the velocities (Δψ̇ = (m/J)·a_ψ), then the pose drifts
    dt·v (``CompiledStep``: the scenario's one dynamics source; A_STEP and B_IMP are its Jacobians)."""
    dt = p[0]
    for i in range(3):
        v = x[3 + i] + (MASS / INERTIA if i == 2 else 1.0) * u[i]
        out[i] = x[i] + dt * v
        out[3 + i] = v


@register
class FreeFlyer(CompiledScenario):
    name: ClassVar[str] = "freeflyer"
    problem_dt: ClassVar[float | None] = DT  # ``step``'s matrices are discretised at DT
    version: ClassVar[str] = "1.0"
    n_steps: ClassVar[int] = N_STEPS
    cost_norm = "l1"
    rel_is_convex: ClassVar[bool] = False
    time_invariant: ClassVar[bool] = True
    exact_linear_dynamics: ClassVar[bool] = True
    dynamics: ClassVar[CompiledStep] = CompiledStep(_step)  # the numpy step, the rollout's model and the fused one
    scp: ClassVar[SCPSettings] = SCPSettings(
        tr_start=10.0, tr_end=0.005, max_iters=20, cost_tol=1e-6, penalty=1e2, feas_tol=1e-4
    )
    # track: above the terminal multipliers of H = 10 windows along open-loop optima, which exceed the paper's 1
    # (bench/tracking_weight.py; measured in docs/evaluation.md, "Tracking weight"); end_horizon and rti: measured in
    # docs/evaluation.md, "End horizon" and "Real-time iteration"
    mpc: ClassVar[MPCWeights] = MPCWeights(
        fuel=1.0, end=9.9, target=1.0, dist=(1, 1, 1, 7, 7, 7), track=3.0, rti="model", end_horizon=50
    )
    state_scale: ClassVar[tuple[float, ...]] = (1.0, 1.0, 1.0, 0.1, 0.1, 0.1)
    control_scale: ClassVar[tuple[float, ...]] = (0.01, 0.01, 0.01)  # Δv [m/s]
    state_labels = ("x [m]", "y [m]", "ψ [rad]", "vx [m/s]", "vy [m/s]", "ω [rad/s]")
    control_labels = ("Δvx [m/s]", "Δvy [m/s]", "aψ [m/s]")

    def sample(self, rng: np.random.Generator) -> Problem:
        x0 = np.zeros(6)
        goal = np.zeros(6)
        x0[:2] = rng.uniform(*START_REGION)
        goal[:2] = rng.uniform(*GOAL_REGION)
        x0[2], goal[2] = rng.uniform(-np.pi, np.pi, size=2)
        return Problem(x0=x0, goal=goal, dt=DT, n_steps=N_STEPS)

    def validate(self, problem: Problem) -> None:
        super().validate(problem)
        for label, p in (("start", problem.x0[:2]), ("goal", problem.goal[:2])):
            d = np.linalg.norm(OBSTACLES - p, axis=1)
            if np.any(d < R_EFF):
                j = int(np.argmin(d))
                raise InfeasibleProblemError(
                    f"freeflyer: {label} {p.round(3).tolist()} lies inside obstacle {j} "
                    f"(distance {d[j]:.3f} m < inflated radius {R_EFF:.3f} m)"
                )
            if np.any(p < TABLE[0]) or np.any(p > TABLE[1]):
                raise InfeasibleProblemError(f"freeflyer: {label} {p.round(3).tolist()} is off the table")

    def control_box(self) -> tuple[np.ndarray, np.ndarray]:
        """The thruster bound's box over all headings: the clusters' Δv, 0.5·(body force component) ± a_ψ/(4·lever),
        within ±Δv_max bound each body component by 2Δv_max and a_ψ by 4·lever·Δv_max; the global impulse, the body
        one rotated by ψ, by 2√2·Δv_max per axis (attained at ψ = 45°)."""
        high = np.array([2 * np.sqrt(2) * DV_MAX, 2 * np.sqrt(2) * DV_MAX, 4 * LEVER * DV_MAX])
        return -high, high

    def step(self, problem: Problem, k: int, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``dynamics`` as two matrix products (up to 1.8× faster than the compiled form; checked against it)."""
        return (x + u @ B_IMP.T) @ A_STEP.T

    def convex_model(self, problem: Problem, window: Window, X_ref: np.ndarray, U_ref: np.ndarray) -> ConvexModel:
        H = window.length
        A = np.broadcast_to(A_STEP, (H, 6, 6))
        B = A_STEP @ B_IMP
        return ConvexModel(A=A, B=np.broadcast_to(B, (H, 6, 3)), c=np.zeros((H, 6)), A_mask=A_STEP != 0, B_mask=B != 0)

    def constraints(
        self, problem: Problem, window: Window, X_ref: np.ndarray, U_ref: np.ndarray, *, obstacles: bool
    ) -> list[ConstraintBlock]:
        H = window.length
        blocks = [self._table_box(H), self._thruster_bound(X_ref, U_ref)]
        if obstacles:
            blocks.append(keepout_block(X_ref[1:, :2], OBSTACLES, R_EFF, steps=np.arange(1, H + 1), n=6))
        return blocks

    @staticmethod
    def _table_box(H: int) -> ConstraintBlock:
        steps = np.arange(1, H + 1)
        G = np.zeros((4, 6))
        G[0, 0], G[1, 1], G[2, 0], G[3, 1] = 1.0, 1.0, -1.0, -1.0
        h = np.concatenate([TABLE[1], -TABLE[0]])
        K = len(steps)
        # hard: each reference iterate satisfies the box, so the subproblem stays feasible without slacks
        return ConstraintBlock(
            "table",
            BlockKind.INEQ,
            steps,
            np.broadcast_to(G, (K, 4, 6)),
            None,
            np.broadcast_to(h, (K, 4)),
            Gx_mask=G != 0,
        )

    @staticmethod
    def _thruster_bound(X_ref: np.ndarray, U_ref: np.ndarray) -> ConstraintBlock:
        """|B_bb(ψ̄) a + A_bb(ψ̄, ā)(ψ − ψ̄)| ≤ Δv_max, the first-order model of |Λ⁻¹R_BG(ψ)a| (paper §V-A (v))."""
        H = len(U_ref)
        psi = X_ref[:H, 2]
        c, s = np.cos(psi), np.sin(psi)
        R_BG = np.zeros((H, 3, 3))
        R_BG[:, 0, 0], R_BG[:, 0, 1], R_BG[:, 1, 0], R_BG[:, 1, 1], R_BG[:, 2, 2] = c, s, -s, c, 1.0
        B_bb = LAMBDA_INV @ R_BG  # (H, 4, 3)
        ax, ay = U_ref[:, 0], U_ref[:, 1]
        u1, u2 = -c * ax - s * ay, -s * ax + c * ay
        A_bb = 0.5 * np.stack([u1, u2, u1, u2], axis=1)  # ∂(Λ⁻¹R_BG(ψ)ā)/∂ψ at ψ̄: (H, 4)
        Gx = np.zeros((H, 4, 6))
        Gx[:, :, 2] = A_bb
        off = A_bb * psi[:, None]
        return ConstraintBlock(
            "thrusters",
            BlockKind.INEQ,
            np.arange(H),
            Gx,
            B_bb,
            DV_MAX + off,
            nonconvex=True,
            soft=True,
            lower=off - DV_MAX,
            Gx_mask=np.arange(6)[None, :].repeat(4, axis=0) == 2,  # only the heading enters
        )

    def violations(self, problem: Problem, X: np.ndarray, start: int = 0) -> np.ndarray:
        d = np.linalg.norm(np.asarray(X)[:, None, :2] - OBSTACLES[None], axis=-1)
        return np.sum(d < R_EFF - VIOLATION_TOL, axis=1)

    def path_violation(
        self, problem: Problem, X: np.ndarray, U: np.ndarray, window: Window, *, obstacles: bool = True
    ) -> float:
        depth = 0.0
        if obstacles:
            depth = np.max(-keepout_distance(X[1:, :2], OBSTACLES, R_EFF), initial=0.0)
        box = np.max(np.concatenate([X[1:, :2] - TABLE[1], TABLE[0] - X[1:, :2]]), initial=0.0)
        thrust = np.max(np.abs(thruster_dv(X[:-1, 2], U)) - DV_MAX, initial=0.0)
        return float(max(depth, box, thrust))

    def problem_from_features(self, x0: np.ndarray, goal: np.ndarray, dt: float, features: dict[str, Any]) -> Problem:
        return Problem(x0=x0, goal=goal, dt=float(dt), n_steps=N_STEPS)

    def batched_model(self, problems: Sequence[Problem], device: Any = "cpu") -> _FreeFlyerModel:
        return _FreeFlyerModel(self.dynamics, self, problems, device)

    def plot(self, ax: Any, problem: Problem, trajectories: dict[str, np.ndarray]) -> None:
        import matplotlib.patches as mpatches

        ax.add_patch(mpatches.Rectangle((0, 0), 3.5, 2.5, fill=False, color="k"))
        for c in OBSTACLES:
            ax.add_patch(mpatches.Circle(c, OBSTACLE_RADIUS, color="tab:red", alpha=0.6))
            ax.add_patch(mpatches.Circle(c, R_EFF, color="tab:red", alpha=0.15))
        for label, X in trajectories.items():
            ax.plot(X[:, 0], X[:, 1], label=label)
        ax.plot(*problem.x0[:2], "ko")
        ax.plot(*problem.goal[:2], "k*", markersize=10)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.legend(loc="upper left", fontsize=8)


class _FreeFlyerModel(CompiledBatchedModel):
    """The compiled step for the fused decoder; in torch the step as two matrix products and the keep-out count,
    batched. The derived torch step is 1.7× faster (``bench/dynamics_forms.py``) but rounds float32 differently (it
    multiplies in float64), and tests/test_dagger.py's expert then fails to converge from one visited state."""

    def step(self, S: Any, A: Any, k: int) -> Any:
        import torch

        a, b = (torch.as_tensor(m, dtype=S.dtype, device=S.device) for m in (A_STEP, B_IMP))
        return (S + A @ b.T) @ a.T

    def violations(self, S: Any, k: int) -> Any:
        import torch

        d = torch.linalg.norm(S[:, None, :2] - torch.as_tensor(OBSTACLES, dtype=S.dtype, device=S.device)[None], dim=-1)
        return (d < R_EFF - VIOLATION_TOL).sum(dim=1).to(S.dtype)
