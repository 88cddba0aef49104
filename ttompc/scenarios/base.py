"""The scenario interface: everything the SCP engine, the datasets, the transformer rollout and MPC need to know
about one optimal-control problem family.

A scenario describes problems of the form (paper Eq. 5)

    min  Σ_k w·c(u_k)                        c = ‖·‖₁ (free-flyer), ‖·‖₂ (RPOD), ½‖·‖₂² (quadrotor)
    s.t. x_{k+1} = f_k(x_k, u_k)             k = 0..N-1, with x_0 = x_start and x_N = x_goal
         convex constraints (boxes, cones, waypoints)
         non-convex constraints (keep-out zones; the free-flyer thruster bound)

on a grid of N controls u_0..u_{N-1} and N+1 states x_0..x_N (x_N is the state after the last control; datasets
store x_0..x_{N-1} like the reference). The engine only ever sees the *convex model* of a window [t, t+H) around a
reference trajectory: affine dynamics (A_k, B_k, c_k) and per-step dense constraint blocks. Scenarios therefore stay
small and declarative, and one engine (``ttompc.solvers.scp``) serves all of them.
"""

from __future__ import annotations

import abc
import enum
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal, Protocol

import numpy as np

from ttompc.errors import InputError

CostNorm = Literal["l1", "l2", "quad"]


class InfeasibleProblemError(InputError):
    """A problem that cannot have a feasible solution (e.g. the start lies inside a keep-out zone): an ``InputError``
    (the CLI prints its one line) that callers such as data generation catch by its own type."""


@dataclass(frozen=True)
class Problem:
    """One sampled problem instance. ``params`` carries scenario-specific data (RPOD: chief orbit, horizon, port).

    Arrays are in the *optimisation* representation of the scenario (RPOD: scaled ROE in metres).
    """

    x0: np.ndarray
    goal: np.ndarray
    dt: float
    n_steps: int
    params: dict[str, Any] = field(default_factory=dict)
    seed: int | None = None

    def __post_init__(self) -> None:
        x0 = np.asarray(self.x0, dtype=np.float64)
        goal = np.asarray(self.goal, dtype=np.float64)
        if x0.ndim != 1 or goal.shape != x0.shape:
            raise ValueError(f"Problem: x0 and goal must be 1-D of equal length, got {x0.shape} and {goal.shape}")
        if not (self.dt > 0 and self.n_steps > 0):
            raise ValueError(f"Problem: dt and n_steps must be positive, got dt={self.dt}, n_steps={self.n_steps}")
        object.__setattr__(self, "x0", x0)
        object.__setattr__(self, "goal", goal)


@dataclass(frozen=True)
class Window:
    """The time window [start, start + length) of a (possibly receding-horizon) subproblem.

    ``reaches_end`` windows carry the terminal condition x_N = goal; others get a terminal cost instead.
    """

    start: int
    length: int
    n_total: int

    def __post_init__(self) -> None:
        if not (0 <= self.start < self.n_total and 1 <= self.length <= self.n_total - self.start):
            raise ValueError(f"Window [{self.start}, {self.start}+{self.length}) outside [0, {self.n_total})")

    @property
    def stop(self) -> int:
        return self.start + self.length

    @property
    def reaches_end(self) -> bool:
        return self.stop == self.n_total

    @property
    def steps(self) -> np.ndarray:
        """Absolute indices of the window's controls (its states are these plus ``stop``)."""
        return np.arange(self.start, self.stop)

    @classmethod
    def full(cls, problem: Problem) -> Window:
        return cls(0, problem.n_steps, problem.n_steps)


@dataclass
class ConvexModel:
    """Affine discrete dynamics of a window: x_{j+1} = A[j] x_j + B[j] u_j + c[j], j = 0..H-1 (window-relative)."""

    A: np.ndarray  # (H, n, n)
    B: np.ndarray  # (H, n, m)
    c: np.ndarray  # (H, n)
    # structural nonzeros of every A[j] (n, n) and B[j] (n, m), for any reference (None: dense); sparse solvers
    # store only these entries, so a mask must also cover entries that are zero only at some references
    A_mask: np.ndarray | None = None
    B_mask: np.ndarray | None = None


class BlockKind(str, enum.Enum):
    INEQ = "ineq"  # Gx x + Gu u <= h            (hard, or soft with an exact L1 penalty on a slack)
    EQ = "eq"  # Gx x + Gu u == h               (hard, or soft with a weighted 2-norm penalty in MPC)
    SOC = "soc"  # ‖Gx[1:] x + Gu[1:] u - h[1:]‖₂ <= Gx[0] x + Gu[0] u - h[0]


@dataclass
class ConstraintBlock:
    """Per-step dense constraint rows on (x_k, u_k) for the listed window-relative steps.

    ``Gx`` (K, M, n), ``Gu`` (K, M, m) or None, ``h`` (K, M). The sparsity pattern is dense per step so that the
    engine can keep one matrix structure and only update values between SCP iterations.
    ``nonconvex`` blocks are linearisations (re-computed from the reference every iteration); ``obstacle`` blocks
    are the ones dropped by the REL relaxation. ``soft`` inequality rows get a slack with an exact penalty.
    """

    name: str
    kind: BlockKind
    steps: np.ndarray  # (K,) window-relative state indices 0..H (index H is the post-final state)
    Gx: np.ndarray
    Gu: np.ndarray | None
    h: np.ndarray
    nonconvex: bool = False
    obstacle: bool = False
    soft: bool = False
    weight: float = 1.0
    lower: np.ndarray | None = None  # INEQ only: lower <= Gx x + Gu u <= h, one shared slack per row pair
    # structural nonzeros of every Gx[k] (M, n) and Gu[k] (M, m), for any reference (None: dense), as in ConvexModel
    Gx_mask: np.ndarray | None = None
    Gu_mask: np.ndarray | None = None

    def __post_init__(self) -> None:
        K = len(self.steps)
        if self.Gx.ndim != 3 or self.Gx.shape[0] != K or self.h.shape != self.Gx.shape[:2]:
            raise ValueError(f"block {self.name!r}: Gx {self.Gx.shape}, h {self.h.shape} do not match {K} steps")
        if self.lower is not None and (self.kind is not BlockKind.INEQ or self.lower.shape != self.h.shape):
            raise ValueError(f"block {self.name!r}: 'lower' needs an INEQ block and the shape of h")
        if self.Gu is not None and self.Gu.shape[:2] != self.Gx.shape[:2]:
            raise ValueError(f"block {self.name!r}: Gu {self.Gu.shape} does not match Gx {self.Gx.shape}")
        if self.Gx_mask is not None and self.Gx_mask.shape != self.Gx.shape[1:]:
            raise ValueError(f"block {self.name!r}: Gx_mask {self.Gx_mask.shape} is not {self.Gx.shape[1:]}")
        if self.Gu_mask is not None and (self.Gu is None or self.Gu_mask.shape != self.Gu.shape[1:]):
            raise ValueError(f"block {self.name!r}: Gu_mask needs Gu and the shape of one step of it")

    @property
    def rows_per_step(self) -> int:
        return self.Gx.shape[1]


@dataclass(frozen=True)
class SCPSettings:
    """Trust-region SCP settings (the authors' schedule, ``docs/design.md``): Δ shrinks geometrically from
    ``tr_start`` to ``tr_end`` over ``max_iters`` iterations; stop when the state step and the cost change are both
    below tolerance."""

    tr_start: float
    tr_end: float
    max_iters: int = 20
    cost_tol: float = 1e-6
    penalty: float = 1e3  # exact-penalty weight on slacks (virtual control, linearised constraints)
    feas_tol: float = 1e-4  # max nonlinear constraint violation accepted as feasible

    @property
    def shrink(self) -> float:
        return float((self.tr_end / self.tr_start) ** (1.0 / self.max_iters))


@dataclass(frozen=True)
class MPCWeights:
    """Soft-mode receding-horizon weights (paper §V: terminal cost ‖x_{t+H} − x̄‖_P; values from the authors' code).

    cost = fuel·Σc(u) + end·‖x_N − goal‖₂ (window reaches the end) or ‖P (x_{t+H} − x̄)‖₂ otherwise, with
    P = target·I for REL-MPC's target, P = track·I for the targets of plan-tracking providers (TTO-MPC,
    PLAN-ONCE, ORACLE-MPC) and P = diag(dist) towards the goal for DIST-MPC.

    ``track`` (None: ``target``, the paper's weight for TTO-MPC too): ‖x_{t+H} − x̄‖₂ is an exact penalty of the
    window's terminal constraint x_{t+H} = x̄ only when the weight exceeds the 2-norm of that constraint's
    multiplier (the marginal cost of moving x̄); below it the window leaves an optimal plan it is given: set it
    above the largest multiplier along open-loop optima (``bench/tracking_weight.py``; docs/evaluation.md, "Tracking
    weight"). ``recommended``'s None settings resolve to ``rti``, the real-time-iteration scope (``RTI_SCOPES``;
    "model"/"end" where one SCP subproblem per step in all / the end windows kept the learned methods' cost), and
    ``end_horizon`` K (windows run to N once N − t <= K; the largest K measured to keep the learned MPC's step 2x
    below REL-MPC@30's on both plants): docs/evaluation.md, "Real-time iteration", "End horizon".
    """

    fuel: float
    end: float
    target: float  # the weight of the window's terminal target term (the paper's; ``mpc.terminal`` names its kind)
    dist: tuple[float, ...]
    waypoint: float = 1.0
    track: float | None = None
    rti: bool | str = False
    end_horizon: int = 30

    @property
    def tracking(self) -> float:
        """The target weight of plan-tracking windows: ``track``, or ``target`` when unset."""
        return self.target if self.track is None else self.track


class BatchedModel(Protocol):
    """Batched torch dynamics in the model representation, for B problems at once.

    ``step(S, A, k)`` maps states (B, n) and controls (B, m) at absolute step k to the next states (B, n);
    ``violations(S, k)`` counts violated keep-out constraints (B,) of states at step k (float tensor).

    Optional (the fused decode kernel, ``ttompc.policy.fused``; without it that kernel is refused and the torch
    rollout runs): ``fused_step()`` -> (step, params): a float32 ``CompiledStep.cfunc`` (``ttompc.scenarios.dynamics``)
    and the problems' parameter rows (B, P) float32, C-contiguous. ``CompiledStep.batched`` makes the whole model
    from the scenario's one step function; ``check-scenario`` checks every form against ``Scenario.step``.
    """

    def step(self, S: Any, A: Any, k: int) -> Any: ...

    def violations(self, S: Any, k: int) -> Any: ...


class Scenario(abc.ABC):
    """A family of optimal-control problems. Subclasses are found by name (``@register``), entry point or spec
    (``ttompc.scenarios.get_scenario``); docs/scenarios.md is the contract on one page."""

    name: ClassVar[str]
    version: ClassVar[str]
    state_dim: ClassVar[int] = 6
    control_dim: ClassVar[int] = 3
    n_steps: ClassVar[int] = 100
    cost_norm: ClassVar[CostNorm]
    rel_is_convex: ClassVar[bool] = False
    exact_linear_dynamics: ClassVar[bool] = False  # affine dynamics independent of the reference: no virtual control
    # dynamics rows whose convex model is an approximation, where virtual control goes (empty: all rows); rows that
    # are exactly linear (e.g. position ← velocity) need none
    approximate_rows: ClassVar[tuple[int, ...]] = ()
    time_invariant: ClassVar[bool] = False  # ``step`` ignores k (and vectorises over leading axes)
    problem_params: ClassVar[tuple[str, ...]] = ()  # the keys of every problem's ``params``, no others (``validate``)
    problem_dt: ClassVar[float | None] = None  # every problem's dt where the scenario fixes it (``validate``)
    scp: ClassVar[SCPSettings]
    mpc: ClassVar[MPCWeights]
    # characteristic magnitudes of states and controls: the engine solves for x/scale, u/scale (non-dimensionalised
    # variables keep the conic solvers well conditioned; the RPOD ROE in metres vs Δv in m/s differ by 1e4)
    state_scale: ClassVar[tuple[float, ...]] = ()
    control_scale: ClassVar[tuple[float, ...]] = ()
    # largest ‖x_N − goal‖ (optimisation representation) of a closed-loop episode counted as reaching the goal; soft
    # MPC end penalties leave a small residual
    terminal_tol: ClassVar[float] = 5e-2
    # the perturbed plant of closed-loop evaluation (ttompc.mpc.plant.PlantNoise): (gain_std, actuation_std,
    # process_std) = a per-episode actuation gain error, actuation noise in units of control_scale and process noise
    # in units of state_scale per step. Sized so that what the last step adds, which no controller can undo, stays
    # inside terminal_tol: the ceiling ORACLE-MPC must still be able to reach the goal.
    perturbation: ClassVar[tuple[float, float, float]] = (0.05, 0.02, 0.002)
    # what backend="auto" means for this scenario, after the Riccati kernel where it starts with PIQP (see
    # ttompc.solvers.backends.backend_chain)
    auto_backends: ClassVar[tuple[str, ...]] = ("piqp", "qoco", "clarabel")
    # trust-region norm of the SCP: "linf" (bounds on the states: a subproblem without cones is a QP) or "l2" (a
    # second-order cone); whichever backend solves it, except the "conic" comparison path (2-norm)
    trust_norm: ClassVar[Literal["l2", "linf"]] = "linf"
    state_labels: ClassVar[tuple[str, ...]]
    control_labels: ClassVar[tuple[str, ...]]

    # ----------------------------------------------------------------------------------------------------- problems
    @abc.abstractmethod
    def sample(self, rng: np.random.Generator) -> Problem:
        """Draw one problem using only ``rng`` (reproducible, no global state)."""

    def validate(self, problem: Problem) -> None:
        """Raise ``InfeasibleProblemError`` for problems that cannot have a solution; ValueError for another shape,
        number of steps, non-finite values, or another scenario's ``problem_params`` keys or ``problem_dt`` (1e-6)."""
        if problem.x0.shape != (self.state_dim,):
            raise ValueError(f"{self.name}: x0 must have shape ({self.state_dim},), got {problem.x0.shape}")
        dt, names = self.problem_dt, (lambda keys: ", ".join(sorted(keys)) or "none")
        if set(problem.params) != set(self.problem_params) or not (dt is None or np.isclose(problem.dt, dt, 1e-6, 0)):
            raise ValueError(
                f"{self.name}: its problems have params {names(self.problem_params)} and dt {dt or 'any'}, this one "
                f"params {names(problem.params)} and dt {problem.dt:g} (another scenario's problem?)"
            )
        if problem.n_steps != self.n_steps:
            raise ValueError(f"{self.name}: problems have {self.n_steps} steps, got {problem.n_steps}")
        if not (np.all(np.isfinite(problem.x0)) and np.all(np.isfinite(problem.goal))):
            raise ValueError(f"{self.name}: x0/goal contain non-finite values")

    # ----------------------------------------------------------------------------------------------------- dynamics
    @abc.abstractmethod
    def step(self, problem: Problem, k: int, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Exact dynamics x_{k+1} = f_k(x_k, u_k) (the 'environment'); vectorised over leading axes of x, u. A
        ``CompiledScenario`` (``ttompc.scenarios.dynamics``) derives it from its dynamics written once."""

    def step_window(self, problem: Problem, start: int, X: np.ndarray, U: np.ndarray) -> np.ndarray:
        """One exact step from each of the states X (H, n) with controls U (H, m) at steps start..start+H−1:
        (H, n). Scenarios whose ``step`` does not depend on k inherit a single vectorised call."""
        if not self.time_invariant:
            return np.stack([self.step(problem, start + j, X[j], U[j]) for j in range(len(U))])
        return self.step(problem, start, X, U)

    def rollout(self, problem: Problem, U: np.ndarray, start: int = 0, x: np.ndarray | None = None) -> np.ndarray:
        """Propagate controls U (H, m) with the exact dynamics from x (default x0) at step ``start``: (H+1, n)."""
        x = problem.x0 if x is None else np.asarray(x, dtype=np.float64)
        out = [x]
        for j, u in enumerate(U):
            x = self.step(problem, start + j, x, u)
            out.append(x)
        return np.stack(out)

    @abc.abstractmethod
    def convex_model(self, problem: Problem, window: Window, X_ref: np.ndarray, U_ref: np.ndarray) -> ConvexModel:
        """Affine model of the dynamics on ``window`` around a reference (H+1, n), (H, m)."""

    # ---------------------------------------------------------------------------------------------- constraints
    @abc.abstractmethod
    def constraints(
        self, problem: Problem, window: Window, X_ref: np.ndarray, U_ref: np.ndarray, *, obstacles: bool
    ) -> list[ConstraintBlock]:
        """Convex constraints plus linearisations of the non-convex ones (obstacle blocks only if ``obstacles``).

        Block *shapes and step sets* must depend only on (problem family, window, obstacles), never on the
        reference values, so that the engine can reuse one matrix structure across SCP iterations.
        Window state 0 is fixed, so keep-out blocks should not include step 0; blocks with controls (Gu) may only
        use steps 0..H-1.
        """

    def trust_region_steps(self, problem: Problem, window: Window, hard_terminal: bool) -> np.ndarray:
        """Window states under the trust region: all free states (1..H−1, plus H when the terminal is soft)."""
        return np.arange(1, window.length + (0 if hard_terminal else 1))

    def state_units(self) -> np.ndarray:
        """``state_scale`` as an array (ones where the scenario gives none): the per-state units in which distances
        between states are measured (plan reuse, target change, oracle detours) and the solvers non-dimensionalise."""
        return units_of(self.state_scale, self.state_dim)

    def control_units(self) -> np.ndarray:
        """``control_scale`` as an array (ones where the scenario gives none), as ``state_units``."""
        return units_of(self.control_scale, self.control_dim)

    def control_box(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(low, high) (m,): a box holding every control the constraints allow at any state, for a bound that
        ``constraints`` does not pose as rows on single control components (those ``ttompc.envs`` reads itself:
        the environments' action space); None (the default): none beyond those."""
        return None

    @abc.abstractmethod
    def violations(self, problem: Problem, X: np.ndarray, start: int = 0) -> np.ndarray:
        """Number of violated keep-out constraints at each state of X (T, n) whose first index is ``start``: (T,)
        int. This is the per-step count behind the constraint-to-go."""

    def constraint_violation(
        self, problem: Problem, X: np.ndarray, U: np.ndarray, window: Window, *, obstacles: bool = True
    ) -> float:
        """Largest violation of the *nonlinear* problem on a window: dynamics defect (one-step, so errors do not
        compound) and the exact path constraints. Used for the feasibility status of SCP iterates."""
        defect = float(np.max(np.abs(self.step_window(problem, window.start, X[:-1], U) - X[1:]), initial=0.0))
        return max(defect, self.path_violation(problem, X, U, window, obstacles=obstacles))

    @abc.abstractmethod
    def path_violation(
        self, problem: Problem, X: np.ndarray, U: np.ndarray, window: Window, *, obstacles: bool = True
    ) -> float:
        """Largest violation of the exact *inequality* path constraints on window states X (H+1, n) and controls
        U (H, m): keep-out depth (only if ``obstacles``), bounds, cones. Window state 0 is fixed and excluded.
        Equality blocks (waypoints) are linear and checked by the engine, which skips them when they are soft."""

    # ----------------------------------------------------------------------------------------------------- cost
    def stage_cost(self, U: np.ndarray) -> np.ndarray:
        """c(u_k) for each row of U (..., m)."""
        return stage_cost(U, self.cost_norm)

    def cost(self, U: np.ndarray) -> float:
        return float(np.sum(self.stage_cost(U)))

    # --------------------------------------------------------------------------------------- representations
    def to_model_states(self, problem: Problem, X: np.ndarray, start: int = 0) -> np.ndarray:
        """Optimisation states (T, n) -> the transformer's state representation (RPOD: RTN). Identity by default."""
        return np.asarray(X, dtype=np.float64)

    def from_model_states(self, problem: Problem, S: np.ndarray, start: int = 0) -> np.ndarray:
        return np.asarray(S, dtype=np.float64)

    def model_goal(self, problem: Problem) -> np.ndarray:
        """Goal in the transformer's state representation."""
        return self.to_model_states(problem, problem.goal[None], start=problem.n_steps)[0]

    @abc.abstractmethod
    def batched_model(self, problems: Sequence[Problem], device: Any = "cpu") -> BatchedModel:
        """The approximate dynamics used by the transformer rollout (paper §IV-B), batched in torch over problems,
        acting on the *model* representation (RPOD: RTN). See ``BatchedModel``; a ``CompiledScenario`` derives it."""

    def problem_features(self, problem: Problem) -> dict[str, np.ndarray]:
        """Flat arrays that, with x0 and goal, reconstruct the problem (stored in datasets)."""
        return {}

    @abc.abstractmethod
    def problem_from_features(self, x0: np.ndarray, goal: np.ndarray, dt: float, features: dict[str, Any]) -> Problem:
        """Inverse of (x0, goal, dt, problem_features)."""

    # ----------------------------------------------------------------------------------------------- guesses
    def initial_guess(
        self, problem: Problem, window: Window | None = None, x_start: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Straight line from the window's first state (default x0) to the goal, zero controls (the reference's
        REL guess): states (H+1, n), controls (H, m)."""
        window = window or Window.full(problem)
        x_start = problem.x0 if x_start is None else np.asarray(x_start, dtype=np.float64)
        s = np.linspace(0.0, 1.0, window.length + 1)[:, None]
        X = (1 - s) * x_start + s * problem.goal
        return X, np.zeros((window.length, self.control_dim))

    # ------------------------------------------------------------------------------------------------ plotting
    def keepout_zones(self, problem: Problem) -> tuple[np.ndarray, np.ndarray]:
        """Keep-out balls over the first d state entries (optimisation representation): centres (K, d), radii (K,).
        The default ``plot`` draws them and ``ttompc check-scenario`` probes states inside them; none by default."""
        return np.zeros((0, 2)), np.zeros(0)

    def plot(self, ax: Any, problem: Problem, trajectories: dict[str, np.ndarray]) -> None:
        """Draw keep-out zones and trajectories (dict label -> optimisation-representation states (T, n) from step
        0) on a matplotlib axis (RPOD accepts an array of axes for several projections). The default draws the
        plane of the first two state entries: the ``keepout_zones`` as discs, the trajectories, start and goal."""
        import matplotlib.patches as mpatches

        centres, radii = self.keepout_zones(problem)
        for c, r in zip(centres, radii, strict=True):
            ax.add_patch(mpatches.Circle(tuple(c[:2]), float(r), color="tab:red", alpha=0.4))
        for label, X in trajectories.items():
            ax.plot(X[:, 0], X[:, 1], label=label)
        ax.plot(*problem.x0[:2], "ko")
        ax.plot(*problem.goal[:2], "k*", markersize=10)
        if len(radii):
            ax.set_aspect("equal")  # discs stay round
        ax.set_xlabel(self.state_labels[0])
        ax.set_ylabel(self.state_labels[1])
        ax.legend(loc="upper left", fontsize=8)


def stage_cost(U: np.ndarray, norm: CostNorm) -> np.ndarray:
    U = np.asarray(U, dtype=np.float64)
    if norm == "l1":
        return np.sum(np.abs(U), axis=-1)
    if norm == "l2":
        return np.linalg.norm(U, axis=-1)
    if norm == "quad":
        return 0.5 * np.sum(U * U, axis=-1)
    raise ValueError(f"unknown cost norm {norm!r}")


def units_of(scale: tuple[float, ...], dim: int) -> np.ndarray:
    """A scale tuple as an array of ``dim`` units (ones where it is empty or does not fit)."""
    return np.asarray(scale, dtype=np.float64) if len(scale) == dim else np.ones(dim)
