"""Warm-start and terminal-target providers of the receding-horizon loop (paper §V-C; the terminal cost
‖x_{t+H} − x̄‖_P of §V, Eq. (8)).

A provider fills the window [t, t+H) with a warm start in the *optimisation* representation (states (H+1, n) whose
first row is the measured state, controls (H, m)) and, for windows that stop before the end, the terminal cost:

* ``RELProvider`` (REL-MPC): REL over the whole remaining horizon [t, N) from x_t, truncated to the window; the
  terminal target x̄ is the REL state at t+H (weights ``mpc.terminal``).
* ``DISTProvider`` (DIST-MPC): REL over the window only, with the distance-to-goal terminal cost diag(``mpc.dist``).
* ``TTOProvider`` (TTO-MPC / FT-TTO-MPC): an H-step transformer rollout from the running ``RolloutContext``
  (conditioned on rtg_0 = −κ·J_REL, ctg_0 = 0); the context is advanced with every executed action and measured
  state, so its KV cache is extended, never recomputed. x̄ = the predicted state at t+H. The TTO providers of B
  episodes run in lockstep (``run_mpc_batch``) can share one batched context (``RolloutGroup``). ``rtg_mode``
  chooses the reward-to-go fed at each step (``RTG_MODES``).
* ``ShiftProvider`` (the DAgger expert): the previous plan shifted by one step (first row replaced by the measured
  state), starting from a given plan; it makes the full-horizon expert cheap.
* ``PlanProvider`` (PLAN-ONCE): one full-horizon plan (the open-loop SCP optimum, solved at t = 0) as warm start and
  terminal target of every window: "plan once, then track", no model, no re-planning. With ``PlanNoise`` it is the
  noisy oracle of ``bench/tto_mpc_robustness.py`` (a stand-in for a model whose plans are off by a known amount).
* ``OracleProvider`` (ORACLE-MPC, the ceiling): the full remaining-horizon SCP optimum from the measured state
  (re-solved, warm-started from its own previous plan, whenever the state leaves the plan), as warm start and
  terminal target — what a perfect model could give.

Terminal targets of TTO-MPC and the plan providers go through a ``TerminalDesign``: the paper's target (the plan's
state at t+H) or the robust variant measured in ``docs/evaluation.md`` (the new target blended with the previous
target shifted by one step), weighted by ``mpc.tracking`` on every component. That weight must exceed the multiplier
of the window's terminal constraint for a window to keep an exact plan (``MPCWeights``); the paper's
``mpc.terminal`` does not on the free-flyer and the quadrotor, so ``mpc.track`` (3 and 2 there) is a departure from the
paper for TTO-MPC, which PLAN-ONCE and ORACLE-MPC share so that they stay its ceilings.

Terminal index: our terminal term penalises x_{t+H}, the state *after* the last window control (the window has
H+1 states). The reference penalised x_{t+H−1}, the last state *before* the last control, which leaves the last
control of every window free of the terminal term.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal, Protocol

import numpy as np

from ttompc.scenarios.base import Problem, Scenario, Window
from ttompc.solvers.scp import SCPResult, TerminalCost, solve_problem, solve_rel, solve_scp

if TYPE_CHECKING:
    from ttompc.policy import Planner, RolloutContext


@dataclass
class WarmStart:
    """A window's initial guess (optimisation representation) and its terminal cost (None if the window reaches
    the end: the loop then imposes the end condition)."""

    X: np.ndarray  # (H+1, n), X[0] = measured state
    U: np.ndarray  # (H, m)
    terminal: TerminalCost | None
    seconds: float | None = None  # this episode's share of work shared with others (None: the loop times the call)


class Provider(Protocol):
    """What the MPC loop asks of a warm-start method."""

    name: str

    def reset(self, scenario: Scenario, problem: Problem, rel_cost: float) -> None:
        """Start an episode; ``rel_cost`` is J_REL of the open-loop REL solution (TTO conditioning)."""

    def warm_start(self, window: Window, x: np.ndarray) -> WarmStart:
        """Warm start of ``window`` from the measured state ``x`` at ``window.start``."""

    def observe(self, u: np.ndarray, x_next: np.ndarray, plan_X: np.ndarray, plan_U: np.ndarray) -> None:
        """The executed control, the measured next state and the solved window plan (for shifting)."""


def _terminal(window: Window, target: np.ndarray, weights: np.ndarray | float) -> TerminalCost | None:
    """The soft terminal term of a window that stops early; None when it reaches the end (the loop decides)."""
    return None if window.reaches_end else TerminalCost(target=target, weights=np.asarray(weights, dtype=np.float64))


@dataclass(frozen=True)
class TerminalDesign:
    """How a plan (a model rollout, an oracle) becomes the terminal cost of a window that stops early.

    ``blend`` β ∈ [0, 1): the target is (1 − β)·x̂_{t+H} + β·(x̄_{t−1} + x̂_{t+H} − x̂_{t+H−1}), the new plan's state
    at t+H blended with the previous target moved on by the new plan's last step. β = 0 is the paper's target. A
    consistent plan gives the same target for every β (the shifted previous target *is* the new one), while
    step-to-step plan noise is averaged over about (1 + β)/(1 − β) steps. ``weights``: per-component terminal
    weights; None = ``mpc.tracking`` on every component (``MPCWeights``)."""

    blend: float = 0.0
    weights: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if not 0.0 <= self.blend < 1.0:
            raise ValueError(f"TerminalDesign.blend must be in [0, 1), got {self.blend}")
        if self.weights is not None and any(w < 0 for w in self.weights):
            raise ValueError(f"TerminalDesign.weights must be >= 0, got {self.weights}")


class TargetFilter:
    """The per-episode state of a ``TerminalDesign``: remembers the previous target."""

    def __init__(self, design: TerminalDesign | None = None) -> None:
        self.design = design or TerminalDesign()
        self.reset()

    def reset(self) -> None:
        self._prev: np.ndarray | None = None
        self._prev_stop = -1

    def __call__(self, scenario: Scenario, window: Window, X: np.ndarray) -> TerminalCost | None:
        """The terminal cost of ``window`` from the provider's window plan ``X`` (H+1, n); None at the end."""
        if window.reaches_end:
            self.reset()
            return None
        target = X[-1].copy()
        beta = self.design.blend
        if beta > 0 and self._prev is not None and self._prev_stop == window.stop - 1 and len(X) >= 2:
            target = (1 - beta) * target + beta * (self._prev + X[-1] - X[-2])
        self._prev, self._prev_stop = target, window.stop
        weights = scenario.mpc.tracking if self.design.weights is None else self.design.weights
        if np.size(weights) not in (1, len(target)):
            raise ValueError(f"terminal weights {weights} do not fit a state of size {len(target)}")
        return TerminalCost(target=target, weights=np.asarray(weights, dtype=np.float64))


class RemainingREL:
    """REL over the whole remaining horizon [t, N) from the measured state, each solve started from the last one's
    plan shifted to t (``solve_rel(guess=...)``) instead of the straight line: the same relaxation from a nearby
    start, about half the time (measured in docs/benchmarks.md, MPC section). The shift spans the steps it was not
    asked for (a controller that reused its plan skips its provider). ``warm=False`` restarts from the straight
    line every step. REL-MPC plans with it; TTO-MPC's ``rtg_mode="reanchor"`` reads its cost."""

    def __init__(self, backend: str = "auto", *, warm: bool = True) -> None:
        self.backend, self.warm = backend, warm
        self._rel: tuple[int, np.ndarray, np.ndarray] | None = None  # (start step, X, U) of the last solve

    def reset(self) -> None:
        self._rel = None

    def __call__(self, scenario: Scenario, problem: Problem, t: int, x: np.ndarray) -> SCPResult:
        rest = Window(t, problem.n_steps - t, problem.n_steps)
        guess = None
        if self.warm and self._rel is not None and 0 < t - self._rel[0] < len(self._rel[2]):
            start, X, U = self._rel
            guess = (X[t - start :], U[t - start :])
        rel = solve_rel(scenario, problem, window=rest, x_start=x, guess=guess, backend=self.backend)
        self._rel = (t, rel.X, rel.U) if rel.success else None
        return rel


class RELProvider:
    """REL-MPC: full remaining-horizon REL (``RemainingREL``), truncated; terminal target = REL state at t+H
    (weight ``mpc.terminal``, the paper's). ``warm_rel=False`` restarts each REL from the straight line."""

    name = "REL-MPC"

    def __init__(self, backend: str = "auto", *, warm_rel: bool = True) -> None:
        self.backend = backend
        self.rel = RemainingREL(backend, warm=warm_rel)

    def reset(self, scenario: Scenario, problem: Problem, rel_cost: float) -> None:
        self.scenario, self.problem = scenario, problem
        self.rel.reset()

    def warm_start(self, window: Window, x: np.ndarray) -> WarmStart:
        sc, p = self.scenario, self.problem
        rel = self.rel(sc, p, window.start, x)
        if rel.success:
            X, U = rel.X[: window.length + 1].copy(), rel.U[: window.length].copy()
        else:  # an unconverged REL is still a usable guess; the straight line is the last resort
            X, U = sc.initial_guess(p, window, x)
        X[0] = x
        return WarmStart(X, U, _terminal(window, X[-1], sc.mpc.terminal))

    def observe(self, u: np.ndarray, x_next: np.ndarray, plan_X: np.ndarray, plan_U: np.ndarray) -> None:
        return None


class DISTProvider:
    """DIST-MPC: REL on the window only, terminal cost ‖diag(dist)(x_{t+H} − goal)‖₂ (no look-ahead)."""

    name = "DIST-MPC"

    def __init__(self, backend: str = "auto") -> None:
        self.backend = backend

    def reset(self, scenario: Scenario, problem: Problem, rel_cost: float) -> None:
        self.scenario, self.problem = scenario, problem

    def warm_start(self, window: Window, x: np.ndarray) -> WarmStart:
        sc, p = self.scenario, self.problem
        terminal = _terminal(window, p.goal, np.asarray(sc.mpc.dist, dtype=np.float64))
        if terminal is None:  # the window reaches the end: the REL carries the end condition itself
            terminal_rel = TerminalCost(p.goal, sc.mpc.end)
        else:
            terminal_rel = terminal
        rel = solve_rel(
            sc,
            p,
            window=window,
            x_start=x,
            terminal=terminal_rel,
            fuel_weight=sc.mpc.fuel,
            soft_equalities=True,
            backend=self.backend,
        )
        X, U = (rel.X.copy(), rel.U.copy()) if rel.success else sc.initial_guess(p, window, x)
        X[0] = x
        return WarmStart(X, U, terminal)

    def observe(self, u: np.ndarray, x_next: np.ndarray, plan_X: np.ndarray, plan_U: np.ndarray) -> None:
        return None


RTGMode = Literal["running", "floor", "reanchor"]
RTG_MODES: tuple[str, ...] = ("running", "floor", "reanchor")
RTG_SIGMAS = 3.0  # the training range's lower end: mean − 3 std of the model's rtg statistics


def check_rtg_scale(value: float, key: str = "rtg_scale") -> None:
    """The conditioning scale κ of rtg_0 = −κ·J_REL must be positive: rewards-to-go are negative costs, so κ <= 0
    asks the model for a trajectory that costs nothing or less; raises ``ValueError`` naming ``key``."""
    if not value > 0:
        raise ValueError(
            f"{key} must be > 0, got {value}: the model is conditioned on rtg_0 = -{key}*J_REL, the reward-to-go "
            f"(minus the cost) of a trajectory costing {key} times REL's; 1 is the paper's, a model's own is in its "
            "bundle"
        )


class TTOProvider:
    """TTO-MPC: H-step rollout from a persistent rollout context (one per episode, KV cache reused; or one batched
    context shared by the providers of a ``group``), conditioned on rtg_0 = −``rtg_scale``·J_REL (None: the model's
    own, ``Planner.rtg_scale``; the paper: 1) and ctg_0 = 0; the target goes through ``design``.

    ``rtg_mode``, the reward-to-go fed at step t (training rows hold rtg_t = −Σ_(τ≥t) c(u_τ), never above 0):

    * ``running`` (the paper, the default): rtg_t = rtg_0 + the cost executed so far. Closed loop the executed cost
      soon exceeds J_REL and rtg_t turns positive, where no training row lives.
    * ``floor``: the running rtg clipped to [μ − 3σ, −``rtg_floor``·|rtg_0|] (μ, σ: the model's rtg statistics), so
      a budget of at least a fraction ``rtg_floor`` of rtg_0 remains.
    * ``reanchor``: rtg_t = −κ·J_REL(t), the REL cost of the remaining horizon [t, N) from the measured state (one
      ``RemainingREL`` per step, as REL-MPC solves; its time counts in the warm start), clipped to the same range;
      the floor value where that REL fails.

    Inside a window the rollout still adds the model's own planned costs to the fed value (the rollout's rule).
    ``use_cache`` and ``clipped`` configure the provider's own group; a given ``group`` has its own."""

    def __init__(
        self,
        planner: Planner,
        name: str = "TTO-MPC",
        *,
        use_cache: bool = True,
        clipped: bool = True,
        rtg_scale: float | None = None,
        design: TerminalDesign | None = None,
        rtg_mode: RTGMode = "running",
        rtg_floor: float = 0.05,
        group: RolloutGroup | None = None,
        backend: str = "auto",
    ) -> None:
        if rtg_mode not in RTG_MODES:
            raise ValueError(f"rtg_mode must be one of {list(RTG_MODES)}, got {rtg_mode!r}")
        if not 0.0 <= rtg_floor < 1.0:
            raise ValueError(f"rtg_floor must be in [0, 1), got {rtg_floor}")
        self.planner, self.name = planner, name
        self.rtg_scale = planner.rtg_scale if rtg_scale is None else rtg_scale
        check_rtg_scale(self.rtg_scale)
        self.rtg_mode, self.rtg_floor = rtg_mode, rtg_floor
        self.target = TargetFilter(design)
        self.group = group or RolloutGroup(planner, use_cache=use_cache, clipped=clipped)
        if self.group.planner is not planner:
            raise ValueError("the providers of a RolloutGroup must share its planner")
        self.slot = self.group.add(self)
        self.rel = RemainingREL(backend)

    @property
    def context(self) -> RolloutContext | None:
        """The rollout context of this provider's group (row ``slot`` is this episode)."""
        return self.group.context

    def reset(self, scenario: Scenario, problem: Problem, rel_cost: float) -> None:
        if scenario.name != self.planner.scenario.name:
            raise ValueError(f"model was trained on {self.planner.scenario.name!r}, not {scenario.name!r}")
        self.scenario, self.problem = scenario, problem
        self.target.reset()
        self.rel.reset()
        self.rtg0 = -self.rtg_scale * rel_cost
        self.spent = 0.0  # Σ c(u) of the executed controls
        self.x = problem.x0
        self.group.join(self.slot)

    def rtg_range(self) -> tuple[float, float]:
        """[μ − 3σ of the model's rtg statistics, −rtg_floor·|rtg_0|]: where training rows' rtg lie."""
        stats = self.planner.stats
        lo = float(stats.mean["rtg"][0] - RTG_SIGMAS * stats.std["rtg"][0])
        hi = -self.rtg_floor * abs(self.rtg0)
        return min(lo, hi), hi

    def conditioning(self, t: int) -> float | None:
        """The rtg to feed at step t (None: the context's running value, ``running``)."""
        if self.rtg_mode == "running":
            return None
        value = self.rtg0 + self.spent  # at t = 0 also reanchor's: rtg_0 = −κ·J_REL(0)
        if self.rtg_mode == "reanchor" and t > 0:
            rel = self.rel(self.scenario, self.problem, t, self.x)
            if rel.success:
                value = -self.rtg_scale * rel.cost
        return float(np.clip(value, *self.rtg_range()))

    def warm_start(self, window: Window, x: np.ndarray) -> WarmStart:
        t0 = time.perf_counter()
        S, U, share, shared = self.group.rollout(self.slot, window)
        X = self.scenario.from_model_states(self.problem, S, start=window.start)
        X[0] = x  # the measured state, exactly (the context holds it in the model dtype)
        ws = WarmStart(X, U, self.target(self.scenario, window, X))
        ws.seconds = time.perf_counter() - t0 - shared + share
        return ws

    def observe(self, u: np.ndarray, x_next: np.ndarray, plan_X: np.ndarray, plan_U: np.ndarray) -> None:
        self.spent += self.scenario.cost(np.asarray(u)[None])
        self.x = np.asarray(x_next)
        k = self.group.t + 1
        s_next = self.scenario.to_model_states(self.problem, self.x[None], start=k)[0]
        self.group.advance(self.slot, u, s_next)


class RolloutGroup:
    """One ``RolloutContext`` for the TTO providers of B episodes run in lockstep (``run_mpc_batch``): the B windows
    of a step come from one batched rollout (a batch-1 rollout is a chain of tiny matmuls, so B episodes cost about
    as much as one), and the context advances once every episode has executed its control. Each episode is charged
    its share of the rollout (``WarmStart.seconds``). A ``TTOProvider`` made without a group has one of its own.

    Lifecycle: providers join at construction (``add``: their slot is their row), the context is built when all of
    them have been ``reset`` for an episode, and every member plans and observes once per step."""

    def __init__(self, planner: Planner, *, use_cache: bool = True, clipped: bool = True) -> None:
        self.planner, self.use_cache, self.clipped = planner, use_cache, clipped
        self.members: list[TTOProvider] = []
        self.context: RolloutContext | None = None
        self._joined: set[int] = set()
        self._pending: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._plan: tuple[tuple[int, int], np.ndarray, np.ndarray, list[float], float] | None = None

    @property
    def t(self) -> int:
        if self.context is None:
            raise RuntimeError("the rollout group's episodes have not all been reset")
        return self.context.t

    def add(self, member: TTOProvider) -> int:
        if self.context is not None or self._joined:
            raise RuntimeError("providers join a RolloutGroup before its first episode")
        self.members.append(member)
        return len(self.members) - 1

    def join(self, slot: int) -> None:
        """``slot``'s episode is reset; the context starts once every member's is."""
        self._joined.add(slot)
        if len(self._joined) < len(self.members):
            self.context = None
            return
        self._joined.clear()
        self._pending.clear()
        self._plan = None
        rtg0 = [m.rtg0 for m in self.members]
        self.context = self.planner.context(
            [m.problem for m in self.members], rtg0=rtg0, ctg0=0.0, use_cache=self.use_cache
        )

    def rollout(self, slot: int, window: Window) -> tuple[np.ndarray, np.ndarray, float, float]:
        """Row ``slot`` of this step's batched rollout (run by the first member to ask): its states (H+1, n) and
        actions (H, m) in the model representation, the member's share of the time (its own conditioning plus
        1/B of the rollout) and the time this call spent on the shared work (0 for all but the first caller)."""
        ctx = self.context
        if ctx is None or ctx.t != window.start:
            raise RuntimeError(f"rollout context is at step {getattr(ctx, 't', None)}, not {window.start}")
        key = (window.start, window.length)
        shared = 0.0
        if self._plan is None or self._plan[0] != key:
            t0 = time.perf_counter()
            own = []
            for m in self.members:
                t1 = time.perf_counter()
                value = m.conditioning(window.start)
                if value is not None:
                    ctx.rtg[m.slot, -1] = value
                own.append(time.perf_counter() - t1)
            t1 = time.perf_counter()
            res = ctx.rollout(window.length, clipped=self.clipped)
            self._sync()
            S, A = res.states.double().cpu().numpy(), res.actions.double().cpu().numpy()
            rollout_time = time.perf_counter() - t1
            shared = time.perf_counter() - t0
            self._plan = (key, S, A, own, rollout_time / len(self.members))
        _, S, A, own, share = self._plan
        return S[slot], A[slot], own[slot] + share, shared

    def advance(self, slot: int, u: np.ndarray, s_next: np.ndarray) -> None:
        """Member ``slot`` executed ``u`` and measured ``s_next`` (model representation); the context advances
        when all members have."""
        if self.context is None:
            raise RuntimeError("the rollout group's episodes have not all been reset")
        self._pending[slot] = (np.asarray(u), np.asarray(s_next))
        if len(self._pending) < len(self.members):
            return
        order = range(len(self.members))
        self.context.advance(np.stack([self._pending[b][0] for b in order]),
                             np.stack([self._pending[b][1] for b in order]))  # fmt: skip
        self._pending.clear()
        self._plan = None
        self._sync()

    def _sync(self) -> None:
        if self.planner.device.type == "cuda":
            import torch

            torch.cuda.synchronize()


class ShiftProvider:
    """The previous plan shifted by one step (DAgger expert); the first plan comes from ``reset_plan``."""

    name = "SHIFT"

    def __init__(self) -> None:
        self.X: np.ndarray | None = None
        self.U: np.ndarray | None = None

    def reset(self, scenario: Scenario, problem: Problem, rel_cost: float) -> None:
        self.scenario, self.problem = scenario, problem
        self.X = self.U = None

    def reset_plan(self, X: np.ndarray, U: np.ndarray) -> None:
        """The plan that warm-starts the first step (e.g. the open-loop REL or SCP solution)."""
        self.X, self.U = np.asarray(X, dtype=np.float64), np.asarray(U, dtype=np.float64)

    def warm_start(self, window: Window, x: np.ndarray) -> WarmStart:
        if self.X is None or self.U is None or len(self.U) < window.length:
            X, U = self.scenario.initial_guess(self.problem, window, x)
        else:
            X, U = self.X[: window.length + 1].copy(), self.U[: window.length].copy()
        X[0] = x
        return WarmStart(X, U, _terminal(window, X[-1], self.scenario.mpc.terminal))

    def observe(self, u: np.ndarray, x_next: np.ndarray, plan_X: np.ndarray, plan_U: np.ndarray) -> None:
        self.X, self.U = plan_X[1:], plan_U[1:]


@dataclass(frozen=True)
class PlanNoise:
    """Seeded error added to a plan, per MPC step, as a rigid offset ε_t of the window's states X[1:] along the
    components ``dims`` (positions): ``independent``: ε_t ~ N(0, std²) drawn afresh every step; ``drift``: an AR(1)
    process ε_t = ρ·ε_{t−1} + √(1 − ρ²)·N(0, std²) with the same stationary std (a slowly wandering, consistent
    error; ρ = ``correlation``). ``std`` is per component, in the optimisation representation (metres)."""

    std: float
    kind: Literal["independent", "drift"] = "independent"
    dims: tuple[int, ...] = (0, 1)
    correlation: float = 0.9
    seed: int = 0

    def __post_init__(self) -> None:
        if self.std < 0 or self.kind not in ("independent", "drift") or not 0 <= self.correlation < 1:
            raise ValueError(f"invalid PlanNoise {self}")


class PlanProvider:
    """PLAN-ONCE: a fixed full-horizon plan (given, or the open-loop SCP optimum solved at t = 0) as warm start and
    terminal target of every window; optional ``noise`` on the plan (the noisy oracle)."""

    def __init__(
        self,
        plan: tuple[np.ndarray, np.ndarray] | None = None,
        *,
        name: str = "PLAN-ONCE",
        noise: PlanNoise | None = None,
        design: TerminalDesign | None = None,
        backend: str = "auto",
    ) -> None:
        self.name, self.noise, self.backend = name, noise, backend
        self._given = plan
        self.target = TargetFilter(design)

    def reset(self, scenario: Scenario, problem: Problem, rel_cost: float) -> None:
        self.scenario, self.problem = scenario, problem
        self.X, self.U = self._given if self._given is not None else full_horizon_plan(scenario, problem, self.backend)
        self.target.reset()
        self._rng = np.random.default_rng(self.noise.seed if self.noise else 0)
        self._eps = np.zeros(len(self.noise.dims)) if self.noise else None

    def _offset(self) -> np.ndarray:
        assert self.noise is not None and self._eps is not None
        draw = self.noise.std * self._rng.standard_normal(len(self.noise.dims))
        if self.noise.kind == "independent":
            self._eps = draw
        else:
            rho = self.noise.correlation
            self._eps = rho * self._eps + np.sqrt(1 - rho**2) * draw
        return self._eps

    def warm_start(self, window: Window, x: np.ndarray) -> WarmStart:
        t, H = window.start, window.length
        X, U = self.X[t : t + H + 1].copy(), self.U[t : t + H].copy()
        if self.noise is not None:
            X[1:, list(self.noise.dims)] += self._offset()
        X[0] = x
        return WarmStart(X, U, self.target(self.scenario, window, X))

    def observe(self, u: np.ndarray, x_next: np.ndarray, plan_X: np.ndarray, plan_U: np.ndarray) -> None:
        return None


def full_horizon_plan(scenario: Scenario, problem: Problem, backend: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """The open-loop SCP optimum warm-started by REL (falls back to the REL solution if the SCP fails)."""
    rel, scp = solve_problem(scenario, problem, backend=backend)
    best = scp if scp is not None and scp.success else rel
    return best.X, best.U


class OracleProvider:
    """ORACLE-MPC: the full remaining-horizon SCP optimum from the measured state (the first plan: given, or REL →
    SCP), as warm start and terminal target. It re-solves [t, N) from its previous plan shifted by one step whenever
    the measured state is off that plan by more than ``replan_tol`` (in units of the scenario's ``state_scale``,
    ∞-norm): on the exact plant the optimum's tail stays optimal (and the MPC follows it within the SCP's
    tolerance), on a perturbed plant it re-plans nearly every step. ``replans`` counts the re-solves."""

    name = "ORACLE-MPC"

    def __init__(
        self,
        plan: tuple[np.ndarray, np.ndarray] | None = None,
        *,
        backend: str = "auto",
        replan_tol: float = 1e-3,
        design: TerminalDesign | None = None,
    ) -> None:
        self._given, self.backend, self.replan_tol = plan, backend, replan_tol
        self.target = TargetFilter(design)

    def reset(self, scenario: Scenario, problem: Problem, rel_cost: float) -> None:
        self.scenario, self.problem = scenario, problem
        X, U = self._given if self._given is not None else full_horizon_plan(scenario, problem, self.backend)
        self.X, self.U = np.array(X, dtype=np.float64), np.array(U, dtype=np.float64)
        self._scale = scenario.state_units()
        self.replans = 0
        self.target.reset()

    def warm_start(self, window: Window, x: np.ndarray) -> WarmStart:
        p = self.problem
        if np.max(np.abs(x - self.X[0]) / self._scale) > self.replan_tol:
            X0 = self.X.copy()
            X0[0] = x
            rest = Window(window.start, p.n_steps - window.start, p.n_steps)
            res = solve_scp(self.scenario, p, X0, self.U, window=rest, backend=self.backend)
            self.replans += 1
            if res.success:
                self.X, self.U = res.X, res.U
        X, U = self.X[: window.length + 1].copy(), self.U[: window.length].copy()
        X[0] = x
        return WarmStart(X, U, self.target(self.scenario, window, X))

    def observe(self, u: np.ndarray, x_next: np.ndarray, plan_X: np.ndarray, plan_U: np.ndarray) -> None:
        self.X, self.U = self.X[1:], self.U[1:]
