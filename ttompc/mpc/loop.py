"""One receding-horizon loop for every scenario and warm-start method (paper §III Eq. (2), §IV-C Eq. (8)).

At each step t (settings: ``MPCSettings``, ``ttompc.mpc.settings``) the provider fills the window
[t, min(t+H, N)) with a warm start and a terminal target; the windowed problem is solved by ``solve_scp`` (the
scenario supplies the full problem's constraints inside the window); the first control is applied with the
*exact* dynamics ``scenario.step``. Soft mode (all paper analyses): fuel weight ``mpc.fuel``, soft equalities, the
provider's terminal cost when the window stops early and ‖x_N − goal‖₂ weighted by ``mpc.end`` when it reaches the
end. Hard mode keeps x_N = goal at the end while the goal is reachable from the window; where it is not (the
penalised solve misses it by more than the SCP's feasibility tolerance), that window is solved as in soft mode (the
soft end term) instead of discarding its plan (counted in ``soft_ends``).

``end_horizon`` (default 0: the paper's fixed H, windows truncated at N; None: the scenario's, as
``MPCSettings.end_horizon_on`` resolves it) is a departure from the paper and the reference: once N − t ≤ end_horizon
the window runs to N (a shrinking horizon at the end), so the goal enters the plan while it is still reachable under
the control bounds.

A failed SCP step is not an exception: the loop applies the next control of the previous plan shifted by one step
(or the warm start's first control at t = 0), counts it in ``fallbacks`` and goes on. Programming errors propagate.
Each step is timed with ``perf_counter``, from the measured state to the control: the observe of the previous step's
outcome (``MPCController.observe``: the provider's update with the executed control and the measured state, TTO's
KV-cache advance; none at t = 0, and the observe after the last control is in no step) + warm start + solve (a CUDA
model synchronises inside its provider). Work shared between lockstep episodes is charged to each its share: a
batched rollout's by the provider (``WarmStart.seconds``), a batched context advance's by the loop from what the
providers report (``Provider.observe``, ``observe_charges``). ``run_mpc_batch`` runs the episodes of B starts
(``EpisodeStart``: problem, J_REL, plant seed) in lockstep as one ``MPCRun`` says (horizon, settings, step cap,
plant), which lets the TTO providers of one ``RolloutGroup`` plan all B windows of a step in one batched rollout;
``run_mpc`` is its B = 1 case.

Three ways a step does less than SCP to convergence from the provider's warm start:

* *Plan reuse* (``reuse``, on by default, results unchanged): a window that reaches the end poses the same
  problem at t + 1 as at t, minus its first step (the same end term and constraints). When the measured state is
  the state this controller's own plan predicted for t + 1 (within ``REUSE_TOL`` in units of ``state_scale``,
  ∞-norm) and that plan met the SCP's stopping rule (a fixed point, not the best iterate of a solve that ran out of
  iterations), the plan's tail is optimal for it (principle of optimality; a re-solve from it returns it after one
  subproblem), so the step applies it without calling the provider or the solver (``StepPlan.reused``). This
  happens on an exact plant in the last windows (all of them with ``end_horizon``) and for the DAgger expert after
  the steps it acted in.
* *Shifted end start* (``end_shift``; ``MPCSettings.shift_for``: the learned methods' controllers only; a
  departure from the paper, which warm-starts every window from its method): where plan reuse does not apply (a
  perturbed plant moved the state off the plan), a window that reaches the end starts its SCP from the tail of this
  controller's previous plan, which reached the end too (so it covers the window; X[0] = the measured state),
  instead of calling the provider: a TTO-MPC step then runs no rollout of up to K steps. The window still solves to
  convergence unless real-time iteration runs there (docs/evaluation.md, "Shifted end start").
* *Real-time iteration* (``rti=True``; ``"model"`` for the controllers of learned providers only, ``"end"`` for their
  windows that reach the end only; never the expert's; one rule, ``MPCSettings.rti_for`` of ``Provider.role``; a
  departure from the paper, which solves every window to convergence): as acados' RTI, one SCP subproblem per step,
  linearised at this controller's previous solution shifted by one step (its missing last step from the provider's
  warm start; X[0] = the measured state), with the provider's terminal target. The first step is solved to
  convergence. The subproblem's solution is applied even when its nonlinear violation exceeds the SCP's tolerance (the
  next step corrects it); only a solver failure falls back. Measured against convergence in docs/evaluation.md.

Every episode starts with ``start_controller`` and steps with two calls of its ``MPCController``: ``plan`` from the
measured state, then, once the control has acted, ``observe`` of its outcome. ``ttompc.mpc.controller.Controller``
(one episode, stepped by the caller) makes the same calls in the same order, so it runs the episodes of
``run_mpc_batch`` (and so of ``evaluate mpc``, the training callback, DAgger and the demo) exactly. Before its first
step ``run_mpc_batch`` compiles what the steps run (``ttompc.mpc.warmup``): no step pays a numba compilation.

The plant is ``ttompc.mpc.plant.Plant``: the exact dynamics, optionally with seeded actuation error and process
noise (``PlantNoise``). An episode's record and feasibility: ``ttompc.mpc.episode``.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ttompc.mpc.episode import Episode, EpisodeTrace, StepPlan
from ttompc.mpc.plant import Plant, PlantNoise
from ttompc.mpc.providers import Provider, WarmStart
from ttompc.mpc.settings import Mode, MPCSettings
from ttompc.mpc.warmup import warm_up
from ttompc.scenarios.base import Problem, Scenario, SCPSettings, Window
from ttompc.solvers.scp import SCPOptions, SCPProblem, SCPResult, SCPStatus, TerminalCost, solve_scp


class MPCController:
    """Solves one window per step from a provider's warm start; remembers its last plan for the fallback, plan reuse
    and real-time iteration (module doc)."""

    def __init__(
        self,
        scenario: Scenario,
        problem: Problem,
        provider: Provider,
        horizon: int,
        settings: MPCSettings | None = None,
    ) -> None:
        if horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        self.scenario, self.problem, self.provider, self.horizon = scenario, problem, provider, horizon
        self.settings = settings or MPCSettings()
        self.rti = self.settings.rti_for(provider.role, scenario)  # real-time iteration: all, "end" or no windows
        self.end_shift = self.settings.shift_for(provider.role)  # end windows start from the own previous plan
        self.end_horizon = self.settings.end_horizon_on(scenario)
        self._scale = scenario.state_units()
        self._plan: tuple[np.ndarray, np.ndarray] | None = None
        self._last: StepPlan | None = None  # the plan this controller made at the previous step
        self._own: StepPlan | None = None  # ... if it was solved (no fallback) and executed: reuse / RTI start
        self._scp = SCPProblem(scenario, problem)  # built once, updated per window (solve)
        self._options = SCPOptions(backend=self.settings.backend)

    def window(self, t: int) -> Window:
        """[t, t + H) truncated at N; the whole rest [t, N) once N − t <= ``end_horizon`` (module doc)."""
        N = self.problem.n_steps
        rest = N - t
        return Window(t, rest if rest <= self.end_horizon else min(self.horizon, rest), N)

    def _terminal(self, window: Window, provided: TerminalCost | None, mode: Mode) -> TerminalCost | None:
        if not window.reaches_end:
            if provided is None:
                raise ValueError(f"provider {self.provider.name!r} gave no terminal cost for window {window}")
            return provided
        if mode == "soft":
            return TerminalCost(self.problem.goal, self.scenario.mpc.end)
        return None  # hard: x_N = goal

    def solve(
        self,
        window: Window,
        X: np.ndarray,
        U: np.ndarray,
        terminal: TerminalCost | None,
        mode: Mode | None = None,
        settings: SCPSettings | None = None,
    ) -> SCPResult:
        """The window's SCP in this controller's mode, or in ``mode`` (hard mode solves a window whose goal is out
        of reach as soft mode does); ``settings`` replace the scenario's (RTI: one iteration)."""
        mode = mode or self.settings.mode
        scp = self._scp.update(window=window, terminal=self._terminal(window, terminal, mode), soft=mode == "soft")
        return solve_scp(scp, X, U, self._options.update(settings=settings))

    def _own_tail(self, window: Window, x: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """The own previous plan shifted by one step, X[0] = x, when it covers ``window``: both reach the end (plan
        reuse, shifted end start; module doc); else None."""
        prev = self._own
        if prev is None or not window.reaches_end or len(prev.U) != window.length + 1:
            return None
        X, U = prev.X[1:].copy(), prev.U[1:].copy()
        X[0] = x
        return X, U

    def _reuse(self, window: Window, x: np.ndarray) -> StepPlan | None:
        """The own previous plan's tail when it is this window's optimum (plan reuse, module doc), else None."""
        prev, tol, tail = self._own, self.settings.reuse_tol, self._own_tail(window, x)
        if tol is None or tail is None or prev is None or not prev.converged:
            return None
        if np.max(np.abs(x - prev.X[1]) / self._scale) > tol:
            return None
        X, U = tail
        return StepPlan(U[0].copy(), X, U, 0.0, 0.0, 0, False, None, prev.soft_end, reused=True, converged=True)

    def _warm_start(self, window: Window, x: np.ndarray) -> WarmStart:
        """The provider's warm start, or under ``end_shift`` the own previous plan's tail (module doc)."""
        tail = self._own_tail(window, x) if self.end_shift else None
        return self.provider.warm_start(window, x) if tail is None else WarmStart(*tail, None)

    def _rti_start(self, window: Window, X: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The own previous solution shifted by one step over the window, its missing tail from the warm start."""
        assert self._own is not None
        k = min(len(self._own.U) - 1, window.length)
        X, U = X.copy(), U.copy()
        X[1 : k + 1], U[:k] = self._own.X[2 : k + 2], self._own.U[1 : k + 1]
        return X, U

    def plan(self, t: int, x: np.ndarray) -> StepPlan:
        """Warm start + SCP for the window at step t from the measured state x."""
        window = self.window(t)
        t0 = time.perf_counter()
        reused = self._reuse(window, x)
        if reused is not None:
            reused.solve_time = time.perf_counter() - t0
            self._last = reused
            return reused
        ws = self._warm_start(window, x)
        t1 = time.perf_counter()
        if ws.X.shape != (window.length + 1, len(x)) or ws.U.shape[0] != window.length:
            raise ValueError(
                f"{self.provider.name}: warm start shapes {ws.X.shape}, {ws.U.shape} do not fit window {window}"
            )
        X0, U0, settings = ws.X, ws.U, None
        rti = self._own is not None and (self.rti is True or (self.rti == "end" and window.reaches_end))
        if rti:
            X0, U0 = self._rti_start(window, ws.X, ws.U)
            settings = dataclasses.replace(self.scenario.scp, max_iters=1)
        res = self.solve(window, X0, U0, ws.terminal, settings=settings)
        iterations, soft_end = res.iterations, False
        if not self._usable(res, rti) and self.settings.mode == "hard" and window.reaches_end:
            # x_N = goal is out of reach (the penalised solve misses it): plan this window as soft mode does (the
            # soft end term) rather than replay the previous plan, which misses it too and is one step staler
            res = self.solve(window, res.X, res.U, None, mode="soft", settings=settings)
            iterations, soft_end = iterations + res.iterations, True
        t2 = time.perf_counter()
        if self._usable(res, rti):
            X, U, fallback = res.X, res.U, False
        elif self._plan is not None and len(self._plan[1]) > 1:
            X, U, fallback = self._plan[0][1:], self._plan[1][1:], True
        else:
            X, U, fallback = ws.X, ws.U, True
        X = np.array(X, dtype=np.float64)
        X[0] = x
        target = None if ws.terminal is None else ws.terminal.target
        warm = t1 - t0 if ws.seconds is None else ws.seconds
        self._last = StepPlan(
            U[0].copy(),
            X,
            np.array(U, dtype=np.float64),
            warm,
            t2 - t1,
            iterations,
            fallback,
            target,
            soft_end,
            converged=not fallback and res.status is SCPStatus.OPTIMAL,
        )
        return self._last

    @staticmethod
    def _usable(res: SCPResult, rti: bool) -> bool:
        """A converged (or feasible) solve; in RTI any subproblem solution (its violation is corrected later)."""
        return res.success or (rti and res.best_iteration >= 0)

    def observe(self, plan: StepPlan, u: np.ndarray, x_next: np.ndarray) -> tuple[float, float | None]:
        """Record the executed control (which may differ from the plan's, e.g. in DAgger) and the next state, and
        pass them to the provider. Returns the seconds the call took and the part of them the provider reports as
        work shared with other episodes (None: none; ``Provider.observe``)."""
        t0 = time.perf_counter()
        self._plan = (plan.X, plan.U)
        own = plan is self._last and not plan.fallback and np.array_equal(u, plan.u)
        self._own = plan if own else None
        shared = self.provider.observe(u, x_next, plan.X, plan.U)
        return time.perf_counter() - t0, shared


def start_controller(
    scenario: Scenario, start: EpisodeStart, provider: Provider, horizon: int, settings: MPCSettings
) -> MPCController:
    """An episode's controller at step 0: ``provider`` reset for ``start`` (its problem and J_REL) and the
    controller over it; ``run_mpc_batch`` and ``ttompc.mpc.controller.Controller`` start every episode with it."""
    provider.reset(scenario, start.problem, start.rel_cost)
    return MPCController(scenario, start.problem, provider, horizon, settings)


def observe_charges(seconds: np.ndarray, shared: Sequence[float | None]) -> np.ndarray:
    """The observe time charged to each of B lockstep episodes for one step: its call's ``seconds`` less the shared
    work its provider reports (``Provider.observe``), plus an even share of all the shared work reported at the step
    among the episodes whose providers report a number (None: the call's whole time is the episode's own)."""
    sharing = np.array([s is not None for s in shared], dtype=bool)
    reported = np.array([0.0 if s is None else s for s in shared], dtype=np.float64)
    charges = np.asarray(seconds, dtype=np.float64) - reported
    if sharing.any():
        charges[sharing] += reported.sum() / sharing.sum()
    return charges


@dataclass(frozen=True)
class EpisodeStart:
    """Where an episode starts: its problem, J_REL of the problem's open-loop REL solution (the lower bound of the
    metrics and the TTO conditioning, rtg_0 = −J_REL) and the seed of the plant's disturbances (same seed, same
    disturbances; unused on the exact plant); ``horizon`` and ``plant`` replace the run's for this episode (None: the
    run's; ``PlantNoise()`` is the exact plant)."""

    problem: Problem
    rel_cost: float
    plant_seed: int = 0
    horizon: int | None = None
    plant: PlantNoise | None = None


@dataclass(frozen=True)
class MPCRun:
    """How a batch of episodes runs (``run_mpc_batch``): planning horizon H, the MPC settings, at most ``max_steps``
    steps per episode (None: all N) and the plant (None: the exact dynamics; a ``PlantNoise``: seeded actuation error
    and process noise, its unset components the scenario's own)."""

    horizon: int
    settings: MPCSettings = field(default_factory=MPCSettings)
    max_steps: int | None = None
    plant: PlantNoise | None = None

    def __post_init__(self) -> None:
        if self.horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {self.horizon}")


class StepHook(Protocol):
    """What acts beside the controllers of a lockstep batch (``run_mpc_batch``), e.g. DAgger's expert."""

    def before(
        self, t: int, controllers: Sequence[MPCController], xs: Sequence[np.ndarray]
    ) -> Sequence[StepPlan | None]:
        """Before step t is planned, from the measured states ``xs``: per episode, the plan that acts at step t
        instead of its controller's (which then does not plan, and observes that plan's outcome), or None."""

    def after(self, t: int, plans: Sequence[StepPlan], xs: Sequence[np.ndarray]) -> None:
        """After step t: the plans that acted and the measured next states."""


def run_mpc(
    scenario: Scenario,
    problem: Problem,
    provider: Provider,
    horizon: int,
    *,
    rel_cost: float,
    settings: MPCSettings | None = None,
    max_steps: int | None = None,
    plant: PlantNoise | None = None,
    plant_seed: int = 0,
) -> Episode:
    """Run receding-horizon control from x0 for N steps (or ``max_steps``) with ``settings`` (default: the paper's)
    on the exact dynamics, or on a perturbed plant (``plant``, disturbances seeded by ``plant_seed``): the B = 1
    case of ``run_mpc_batch``, spelled out for scripts.

    ``rel_cost`` is J_REL of the open-loop REL solution: the lower bound of the metrics and the TTO conditioning
    (rtg_0 = −J_REL)."""
    run = MPCRun(horizon, settings or MPCSettings(), max_steps, plant)
    return run_mpc_batch(scenario, [EpisodeStart(problem, rel_cost, plant_seed)], [provider], run)[0]


def run_mpc_batch(
    scenario: Scenario,
    starts: Sequence[EpisodeStart],
    providers: Sequence[Provider],
    run: MPCRun,
    on_step: Callable[[], None] | None = None,
    hook: StepHook | None = None,
) -> list[Episode]:
    """The episodes of B ``starts`` (one provider each) run as ``run`` says, in lockstep: at every step all B
    episodes plan, then all B act. Each episode is what it gives when run alone (for TTO up to the rounding of a
    batched rollout); stepping together lets providers share work across episodes (the TTO providers of one
    ``RolloutGroup``: one batched rollout and one batched context advance per step), and each episode's step times
    hold its share of that work (module doc). ``on_step`` is called after every step (progress); ``hook`` acts beside
    the controllers (``StepHook``: a plan it gives acts instead of the controller's)."""
    B = len(starts)
    if len(providers) != B:
        raise ValueError(f"{B} episodes need as many providers, got {len(providers)}")
    problems = [s.problem for s in starts]
    if len({p.n_steps for p in problems}) > 1:
        raise ValueError("episodes run in lockstep need problems of one length N")
    if B == 0:
        return []
    N = problems[0].n_steps
    T = N if run.max_steps is None else min(run.max_steps, N)
    horizons = [run.horizon if s.horizon is None else s.horizon for s in starts]
    # each episode's plant, None components the scenario's own; None: the exact dynamics
    noises = [
        None if n is None else n.resolve(scenario) for n in (run.plant if s.plant is None else s.plant for s in starts)
    ]
    warm_up(scenario, problems[0], providers, max(horizons), run.settings)  # no compilation inside a step
    ctrls, sims = [], []
    for start, provider, horizon, noise in zip(starts, providers, horizons, noises, strict=True):
        ctrls.append(start_controller(scenario, start, provider, horizon, run.settings))
        sim = Plant(scenario, noise)
        sim.reset(start.plant_seed)
        sims.append(sim)
    xs = [p.x0.copy() for p in problems]
    traces = [EpisodeTrace(x, T) for x in xs]
    for t in range(T):
        given = [None] * B if hook is None else hook.before(t, ctrls, xs)
        plans = [ctrl.plan(t, x) if g is None else g for ctrl, x, g in zip(ctrls, xs, given, strict=True)]
        seconds = np.zeros(B)  # each episode's observe call (s), and the shared work its provider reported in it
        shared: list[float | None] = [None] * B
        for b, plan in enumerate(plans):
            xs[b] = sims[b].step(problems[b], t, xs[b], plan.u)
            seconds[b], shared[b] = ctrls[b].observe(plan, plan.u, xs[b])
            traces[b].record(t, plan, xs[b])
        if hook is not None:
            hook.after(t, plans, xs)
        if t + 1 < T:  # the last step's outcome is observed but planned from by no step
            for trace, charge in zip(traces, observe_charges(seconds, shared), strict=True):
                trace.observed[t + 1] = charge
        if on_step is not None:
            on_step()
    rows = zip(traces, starts, providers, horizons, noises, ctrls, strict=True)
    return [
        trace.episode(scenario, start.problem, provider.name, horizon, start.rel_cost, noise, ctrl.rti)
        for trace, start, provider, horizon, noise, ctrl in rows
    ]
