"""A 2-D double integrator that must steer around one circular keep-out zone: the worked example of
docs/scenarios.md, small enough to read in one sitting and to train on in minutes.

State x = [px, py, vx, vy] (m, m/s), control u = [ax, ay] (m/s²), cost Σ ½‖u‖². The dynamics are the exact
zero-order-hold step of p̈ = u, written once (``step``, a ``CompiledStep``: the environment, the SCP's convex model
and its Jacobians, the transformer's batched model and the fused decoder's compiled step all come from it); the
dynamics are linear, so the convex model is exact (no virtual control), and the keep-out disc is the only
non-convex constraint, linearised by the shared tangent half-spaces of ``ttompc.scenarios.keepout``.

Use it without installing anything:

    ttompc check-scenario examples/di2d.py:DoubleIntegrator2D
    ttompc solve scenario=examples/di2d.py:DoubleIntegrator2D seed=3 plot=di2d.png
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

import ttompc.scenarios.dynamics as compiled
from ttompc.scenarios import (
    BlockKind,
    ConstraintBlock,
    InfeasibleProblemError,
    MPCWeights,
    Problem,
    SCPSettings,
    Window,
)
from ttompc.scenarios.keepout import keepout_block, keepout_distance

DT = 0.25  # s
N_STEPS = 40  # a 10 s manoeuvre
U_MAX = 1.0  # m/s² per axis
CENTRE = np.array([[0.0, 0.0]])  # one keep-out disc (K = 1 zones, d = 2 position entries)
RADIUS = np.array([1.0])  # m
START = (np.array([-3.0, -1.0]), np.array([-2.5, 1.0]))  # box of start positions (at rest)
GOAL = (np.array([2.5, -1.0]), np.array([3.0, 1.0]))  # box of goal positions (at rest)
VIOLATION_TOL = 1e-5  # m: a solution touching the disc is not a violation


def step(x: Any, u: Any, k: int, p: Any, out: Any) -> None:
    """x_{k+1} from x (4,), u (2,) at step k with p = [dt], written into out (4,): plain Python on scalars that numba
    compiles (``CompiledStep``)."""
    dt = p[0]
    for i in range(2):
        out[i] = x[i] + dt * x[2 + i] + 0.5 * dt * dt * u[i]
        out[2 + i] = x[2 + i] + dt * u[i]


class DoubleIntegrator2D(compiled.CompiledScenario):
    name: ClassVar[str] = "di2d"
    version: ClassVar[str] = "1.0"
    state_dim: ClassVar[int] = 4
    control_dim: ClassVar[int] = 2
    n_steps: ClassVar[int] = N_STEPS
    cost_norm = "quad"
    exact_linear_dynamics: ClassVar[bool] = True  # A, B do not depend on the reference: no virtual control
    rel_is_convex: ClassVar[bool] = True  # without the disc the problem is a QP: REL is one solve
    time_invariant: ClassVar[bool] = True  # ``step`` ignores k and vectorises over leading axes
    dynamics = compiled.CompiledStep(step)  # step(), convex_model(), batched_model() and the fused step: one source
    # Δ bounds every state entry's change per SCP iteration, in state units: 2 m lets the first iteration swing
    # the straight line around the disc; 1e-3 m is where it stops. docs/scenarios.md measures other choices.
    scp: ClassVar[SCPSettings] = SCPSettings(tr_start=2.0, tr_end=1e-3, max_iters=20, penalty=1e2, feas_tol=1e-4)
    # soft MPC: weights of the norms ‖x_N − goal‖ (end), ‖x_{t+H} − x̄‖ (target, REL-/TTO-MPC) and
    # ‖diag(dist)(x_{t+H} − goal)‖ (DIST-MPC) against the fuel Σ ½‖u‖²; chosen by bench/scenario_settings.py
    mpc: ClassVar[MPCWeights] = MPCWeights(fuel=1.0, end=10.0, target=3.0, dist=(1.0, 1.0, 1.0, 1.0))
    state_scale: ClassVar[tuple[float, ...]] = (1.0, 1.0, 0.5, 0.5)  # m, m, m/s, m/s: typical magnitudes
    control_scale: ClassVar[tuple[float, ...]] = (0.2, 0.2)  # m/s²
    terminal_tol: ClassVar[float] = 5e-2
    state_labels = ("x [m]", "y [m]", "vx [m/s]", "vy [m/s]")
    control_labels = ("ax [m/s²]", "ay [m/s²]")

    # ----------------------------------------------------------------------------------------------------- problems
    def sample(self, rng: np.random.Generator) -> Problem:
        x0 = np.concatenate([rng.uniform(*START), np.zeros(2)])
        goal = np.concatenate([rng.uniform(*GOAL), np.zeros(2)])
        return Problem(x0=x0, goal=goal, dt=DT, n_steps=N_STEPS)

    def validate(self, problem: Problem) -> None:
        super().validate(problem)
        for label, p in (("start", problem.x0[:2]), ("goal", problem.goal[:2])):
            if keepout_distance(p[None], CENTRE, RADIUS)[0, 0] <= 0:
                raise InfeasibleProblemError(f"di2d: {label} {p.round(3).tolist()} lies inside the keep-out disc")

    def problem_from_features(self, x0: np.ndarray, goal: np.ndarray, dt: float, features: dict[str, Any]) -> Problem:
        return Problem(x0=x0, goal=goal, dt=float(dt), n_steps=N_STEPS)

    # ---------------------------------------------------------------------------------------------- constraints
    def constraints(
        self, problem: Problem, window: Window, X_ref: np.ndarray, U_ref: np.ndarray, *, obstacles: bool
    ) -> list[ConstraintBlock]:
        H = window.length
        box = ConstraintBlock(  # -U_MAX <= u_j <= U_MAX on the window's controls 0..H-1
            "control_box",
            BlockKind.INEQ,
            np.arange(H),
            np.zeros((H, 2, 4)),
            np.broadcast_to(np.eye(2), (H, 2, 2)).copy(),
            np.full((H, 2), U_MAX),
            lower=np.full((H, 2), -U_MAX),
        )
        if not obstacles:
            return [box]
        # states 1..H (state 0 is fixed), tangent half-spaces at the reference's radial projection on the disc
        return [box, keepout_block(X_ref[1:, :2], CENTRE, RADIUS, steps=np.arange(1, H + 1), n=4)]

    def violations(self, problem: Problem, X: np.ndarray, start: int = 0) -> np.ndarray:
        return np.sum(keepout_distance(np.asarray(X)[:, :2], CENTRE, RADIUS) < -VIOLATION_TOL, axis=1)

    def path_violation(
        self, problem: Problem, X: np.ndarray, U: np.ndarray, window: Window, *, obstacles: bool = True
    ) -> float:
        depth = -np.min(keepout_distance(X[1:, :2], CENTRE, RADIUS), initial=0.0) if obstacles else 0.0
        return float(max(depth, np.max(np.abs(U) - U_MAX, initial=0.0)))

    def keepout_zones(self, problem: Problem) -> tuple[np.ndarray, np.ndarray]:
        return CENTRE, RADIUS
