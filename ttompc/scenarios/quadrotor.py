"""Quadrotor crossing a forest of four spherical obstacles (paper §V-A; the authors' 'random_target_forest' setting).

State x = [p, v] (m, m/s), control u = thrust force (N). Continuous dynamics ṗ = v, v̇ = u/m − (c_d/m)‖v‖v are
stepped with explicit Euler, written once (``_step``, a ``CompiledStep``: the environment, the transformer's model and
the fused decoder's step). The convex model is the first-order Taylor expansion of that Euler step about the
reference (its Jacobians by hand, 1.6× faster than derived ones, ``bench/dynamics_forms.py``; checked against the
step by ``check-scenario``), so REL (obstacles off) is itself an SCP.
"""

from __future__ import annotations

import functools
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

MASS = 32.0  # kg
DRAG = 0.2  # c_d (kg/m): drag force −c_d‖v‖v
U_MAX = 10.0  # N per component
DT = 1.0  # s
N_STEPS = 100
START_REGION = (np.array([-2.0, -0.5, 0.2]), np.array([-1.75, 0.5, 0.6]))
GOAL_REGION = (np.array([-0.2, -0.5, 0.2]), np.array([0.5, 0.5, 0.6]))
OBSTACLES = np.array([[-1.4, -0.1, 0.3], [-0.7, 0.3, 0.5], [-0.3, 0.25, 0.65], [0.0, -0.3, 0.4]])
OBSTACLE_RADII = np.array([0.3, 0.2, 0.2, 0.2])  # nominal radii, no inflation (as in the reference OCP and ctg)
VIOLATION_TOL = 1e-5  # m; an SCP solution touching an obstacle is not a violation


def drag_jacobian(v: np.ndarray) -> np.ndarray:
    """∂(−(c_d/m)‖v‖v)/∂v = −(c_d/m)(‖v‖I + vvᵀ/‖v‖) (..., 3, 3); the limit at v = 0 is 0 (the drag is O(‖v‖²)),
    so no ε in the denominator is needed (the reference adds 1e-6)."""
    norm = np.linalg.norm(v, axis=-1)[..., None, None]
    outer = v[..., :, None] * v[..., None, :]
    J = norm * np.eye(3) + np.divide(outer, norm, out=np.zeros_like(outer), where=norm > 0)
    return -(DRAG / MASS) * J


def _step(x: Any, u: Any, k: int, p: Any, out: Any) -> None:
    """The explicit-Euler step with quadratic drag, p = [dt] (``CompiledStep``: the scenario's one dynamics source)."""
    dt = p[0]
    speed = np.sqrt(x[3] * x[3] + x[4] * x[4] + x[5] * x[5])
    for i in range(3):
        out[i] = x[i] + dt * x[3 + i]
        out[3 + i] = x[3 + i] + dt * (u[i] / MASS - (DRAG / MASS) * speed * x[3 + i])


@register
class Quadrotor(CompiledScenario):
    name: ClassVar[str] = "quadrotor"
    problem_dt: ClassVar[float | None] = DT
    version: ClassVar[str] = "1.0"
    n_steps: ClassVar[int] = N_STEPS
    cost_norm = "quad"
    rel_is_convex: ClassVar[bool] = False
    time_invariant: ClassVar[bool] = True
    exact_linear_dynamics: ClassVar[bool] = False
    approximate_rows: ClassVar[tuple[int, ...]] = (3, 4, 5)  # only the velocity update carries the drag
    dynamics: ClassVar[CompiledStep] = CompiledStep(_step)  # step, the rollout's model and the fused one
    # Penalty 1e2: the multipliers of the dynamics/obstacle rows are O(m·‖u‖) ≲ 10 for forces of a few newtons, so
    # slacks vanish at the solution. feas_tol 1e-6 on the one-step defect: it compounds in the open-loop
    # environment roughly as Σ_k (N−k)·d ≈ 5e3·d in position, so 1e-6 keeps rollouts within ~5 mm of the plan and
    # rejects early iterates that cut corners through the linearisation error ((c_d/m)·‖δv‖²·dt ≈ 6e-5 for
    # ‖δv‖ = 0.1 m/s); converged iterates have defects of 1e-8 or less.
    scp: ClassVar[SCPSettings] = SCPSettings(
        tr_start=10.0, tr_end=0.005, max_iters=20, cost_tol=1e-6, penalty=1e2, feas_tol=1e-6
    )
    # track: above the terminal multipliers of H = 10 windows along open-loop optima, which exceed the paper's 1 at
    # the end of the braking phase (bench/tracking_weight.py; measured in docs/evaluation.md, "Tracking weight");
    # end_horizon 50 with real-time iteration in the learned methods' end windows (rti "end"): measured in
    # docs/evaluation.md, "End horizon" (converged end windows cost the learned step its 2x lead on the perturbed plant)
    mpc: ClassVar[MPCWeights] = MPCWeights(
        fuel=1.0, end=10.0, target=1.0, dist=(0.08,) * 6, track=2.0, rti="end", end_horizon=50
    )
    state_scale: ClassVar[tuple[float, ...]] = (1.0, 1.0, 1.0, 0.1, 0.1, 0.1)
    control_scale: ClassVar[tuple[float, ...]] = (0.1, 0.1, 0.1)  # N
    state_labels = ("x [m]", "y [m]", "z [m]", "vx [m/s]", "vy [m/s]", "vz [m/s]")
    control_labels = ("Fx [N]", "Fy [N]", "Fz [N]")

    # ----------------------------------------------------------------------------------------------------- problems
    def sample(self, rng: np.random.Generator) -> Problem:
        x0 = np.concatenate([_sample_free(rng, START_REGION), np.zeros(3)])
        goal = np.concatenate([_sample_free(rng, GOAL_REGION), np.zeros(3)])
        return Problem(x0=x0, goal=goal, dt=DT, n_steps=N_STEPS)

    def validate(self, problem: Problem) -> None:
        super().validate(problem)
        for label, p in (("start", problem.x0[:3]), ("goal", problem.goal[:3])):
            clearance = keepout_distance(p[None], OBSTACLES, OBSTACLE_RADII)[0]
            if np.any(clearance <= 0):
                j = int(np.argmin(clearance))
                raise InfeasibleProblemError(
                    f"quadrotor: {label} {p.round(3).tolist()} lies inside obstacle {j} "
                    f"(clearance {clearance[j]:.3f} m)"
                )

    # ----------------------------------------------------------------------------------------------------- dynamics
    def convex_model(self, problem: Problem, window: Window, X_ref: np.ndarray, U_ref: np.ndarray) -> ConvexModel:
        """x_{j+1} ≈ A_j x_j + B_j u_j + c_j: the Euler step linearised at (x̄_j, ū_j); it is exact at the reference
        (c_j = dt·(c_d/m)‖v̄‖v̄ in the velocity rows) and affine in u, so only the drag contributes an error."""
        H, dt = window.length, problem.dt
        v = X_ref[:H, 3:]
        A = np.broadcast_to(np.eye(6), (H, 6, 6)).copy()
        A[:, :3, 3:] += dt * np.eye(3)
        A[:, 3:, 3:] += dt * drag_jacobian(v)
        B = np.zeros((H, 6, 3))
        B[:, 3:, :] = dt / MASS * np.eye(3)
        c = np.zeros((H, 6))
        c[:, 3:] = dt * (DRAG / MASS) * np.linalg.norm(v, axis=-1, keepdims=True) * v
        return ConvexModel(A=A, B=B, c=c, A_mask=_A_MASK, B_mask=_B_MASK)

    # ---------------------------------------------------------------------------------------------- constraints
    def constraints(
        self, problem: Problem, window: Window, X_ref: np.ndarray, U_ref: np.ndarray, *, obstacles: bool
    ) -> list[ConstraintBlock]:
        H = window.length
        blocks = [_control_box(H)]
        if obstacles:
            blocks.append(keepout_block(X_ref[1:, :3], OBSTACLES, OBSTACLE_RADII, steps=np.arange(1, H + 1), n=6))
        return blocks

    def violations(self, problem: Problem, X: np.ndarray, start: int = 0) -> np.ndarray:
        clearance = keepout_distance(np.asarray(X)[:, :3], OBSTACLES, OBSTACLE_RADII)
        return np.sum(clearance < -VIOLATION_TOL, axis=1)

    def path_violation(
        self, problem: Problem, X: np.ndarray, U: np.ndarray, window: Window, *, obstacles: bool = True
    ) -> float:
        depth = 0.0
        if obstacles:
            depth = -np.min(keepout_distance(X[1:, :3], OBSTACLES, OBSTACLE_RADII), initial=0.0)
        box = np.max(np.abs(U) - U_MAX, initial=0.0)
        return float(max(depth, box))

    def problem_from_features(self, x0: np.ndarray, goal: np.ndarray, dt: float, features: dict[str, Any]) -> Problem:
        return Problem(x0=x0, goal=goal, dt=float(dt), n_steps=N_STEPS)

    def batched_model(self, problems: Sequence[Problem], device: Any = "cpu") -> _QuadrotorModel:
        return _QuadrotorModel(self.dynamics, self, problems, device)

    def plot(self, ax: Any, problem: Problem, trajectories: dict[str, np.ndarray]) -> None:
        """Top view (x–y) with the obstacles' horizontal cross-sections at their centres."""
        import matplotlib.patches as mpatches

        for c, r in zip(OBSTACLES, OBSTACLE_RADII, strict=True):
            ax.add_patch(mpatches.Circle(c[:2], r, color="tab:red", alpha=0.4))
        for label, X in trajectories.items():
            ax.plot(X[:, 0], X[:, 1], label=label)
        ax.plot(*problem.x0[:2], "ko")
        ax.plot(*problem.goal[:2], "k*", markersize=10)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.legend(loc="upper left", fontsize=8)


def _sample_free(rng: np.random.Generator, region: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Rejection-sample a position in the box outside every obstacle."""
    while True:
        p = rng.uniform(*region)
        if np.all(keepout_distance(p[None], OBSTACLES, OBSTACLE_RADII) > 0):
            return p


# structural nonzeros of the linearised Euler step: identity, dt·I (position ← velocity), the drag Jacobian block
_A_MASK = np.eye(6, dtype=bool) | np.block([[np.zeros((3, 3)), np.eye(3)], [np.zeros((3, 3)), np.ones((3, 3))]]).astype(
    bool
)
_B_MASK = np.vstack([np.zeros((3, 3)), np.eye(3)]).astype(bool)


@functools.lru_cache(maxsize=128)
def _control_box(H: int) -> ConstraintBlock:
    """−U_MAX ≤ u_j ≤ U_MAX componentwise as hard two-sided rows on the controls of window steps 0..H−1 (constant:
    built once per window length, read-only)."""
    arrays = [
        np.arange(H),
        np.zeros((H, 3, 6)),
        np.broadcast_to(np.eye(3), (H, 3, 3)).copy(),
        np.full((H, 3), U_MAX),
        np.full((H, 3), -U_MAX),
    ]
    for a in arrays:
        a.flags.writeable = False
    steps, Gx, Gu, h, lower = arrays
    return ConstraintBlock(
        "control_box",
        BlockKind.INEQ,
        steps,
        Gx,
        Gu,
        h,
        lower=lower,
        Gx_mask=np.zeros((3, 6), bool),
        Gu_mask=np.eye(3, dtype=bool),
    )


class _QuadrotorModel(CompiledBatchedModel):
    """The compiled step, with the keep-out count batched in torch."""

    def violations(self, S: Any, k: int) -> Any:
        import torch

        obs, radii = (torch.as_tensor(a, dtype=S.dtype, device=S.device) for a in (OBSTACLES, OBSTACLE_RADII))
        d = torch.linalg.norm(S[:, None, :3] - obs[None], dim=-1) - radii
        return (d < -VIOLATION_TOL).sum(dim=1).to(S.dtype)
