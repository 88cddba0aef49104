"""One receding-horizon loop for every scenario and warm-start method (paper §III Eq. (2), §IV-C Eq. (8)).

At each step t: the provider fills the window [t, min(t+H, N)) with a warm start and a terminal target; the
windowed problem is solved by ``solve_scp`` (the scenario supplies the full problem's constraints inside the
window); the first control is applied with the *exact* dynamics ``scenario.step``. Soft mode (all paper analyses):
fuel weight ``mpc.fuel``, soft equalities, the provider's terminal cost when the window stops early and
‖x_N − goal‖₂ weighted by ``mpc.end`` when it reaches the end. Hard mode keeps x_N = goal at the end.

A failed SCP step is not an exception: the loop applies the next control of the previous plan shifted by one step
(or the warm start's first control at t = 0), counts it in ``fallbacks`` and goes on. Programming errors propagate.
Each step is timed with ``perf_counter`` (warm start + solve; a CUDA model synchronises inside its provider).

The plant is ``ttompc.mpc.plant.Plant``: the exact dynamics, optionally with seeded actuation error and process
noise (``PlantNoise``). Plan consistency is recorded per episode: ``target_change`` is the mean over consecutive
steps of ‖(x̄_t − x̄_{t−1}) / state_scale‖₂, the change of the terminal target between MPC steps in units of the
scenario's characteristic magnitudes (a consistent plan moves it by about one step of motion; a jittering one by
much more).
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ttompc.mpc.plant import Plant, PlantNoise
from ttompc.mpc.providers import Provider
from ttompc.scenarios.base import Problem, Scenario, Window
from ttompc.solvers.scp import SCPResult, TerminalCost, solve_scp

Mode = Literal["soft", "hard"]
# Episodes count as reaching the goal when ‖x_N − goal‖₂ <= scenario.terminal_tol: the soft end penalty cannot cancel
# a residual velocity below one step's thrust (free-flyer: 0.01 m/s per step; REL-MPC at H = 10 ends ~0.0105 away).


@dataclass
class StepPlan:
    """The outcome of one MPC step: the control to apply and the window plan it came from."""

    u: np.ndarray
    X: np.ndarray  # (H+1, n) solved (or fallback) window plan
    U: np.ndarray  # (H, m)
    warm_time: float
    solve_time: float
    iterations: int
    fallback: bool
    target: np.ndarray | None = None  # the window's terminal target (None when the window reaches the end)


@dataclass
class Episode:
    """A closed-loop run: executed trajectory (T+1 states, T controls; T = N unless ``max_steps``) and metrics."""

    method: str
    horizon: int
    X: np.ndarray
    U: np.ndarray
    cost: float  # Σ c(u) of the executed controls
    rel_cost: float  # J_REL of the open-loop REL solution (lower bound of the full problem)
    step_times: np.ndarray  # (T,) warm start + solve per step (s)
    warm_times: np.ndarray
    solve_times: np.ndarray
    iterations: np.ndarray  # (T,) SCP iterations per step
    fallbacks: int
    terminal_error: float  # ‖x_N − goal‖₂ (nan for truncated episodes)
    keepout_violations: int  # states of the executed trajectory inside a keep-out zone
    path_violation: float  # largest exact path-constraint violation (keep-out depth, bounds, ...)
    complete: bool  # ran all N steps
    feasible: bool  # no keep-out violation, path violation ≤ tol and (if complete) terminal error ≤ tol
    target_change: float = float("nan")  # plan consistency (module doc); nan without two consecutive targets
    plant: str = "nominal"  # "nominal" or "perturbed"

    def summary(self) -> dict[str, float | int | str | bool]:
        return {
            "method": self.method,
            "horizon": self.horizon,
            "cost": self.cost,
            "rel_cost": self.rel_cost,
            "steps": len(self.U),
            "mean_step_time": float(np.mean(self.step_times)) if len(self.step_times) else float("nan"),
            "max_step_time": float(np.max(self.step_times)) if len(self.step_times) else float("nan"),
            "mean_iterations": float(np.mean(self.iterations)) if len(self.iterations) else float("nan"),
            "fallbacks": self.fallbacks,
            "terminal_error": self.terminal_error,
            "keepout_violations": self.keepout_violations,
            "path_violation": self.path_violation,
            "complete": self.complete,
            "feasible": self.feasible,
            "target_change": self.target_change,
            "plant": self.plant,
        }


class MPCController:
    """Solves one window per step from a provider's warm start; remembers its last plan for the fallback."""

    def __init__(
        self,
        scenario: Scenario,
        problem: Problem,
        provider: Provider,
        horizon: int,
        *,
        mode: Mode = "soft",
        backend: str = "auto",
    ) -> None:
        if horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        if mode not in ("soft", "hard"):
            raise ValueError(f"mode must be 'soft' or 'hard', got {mode!r}")
        self.scenario, self.problem, self.provider = scenario, problem, provider
        self.horizon, self.mode, self.backend = horizon, mode, backend
        self._plan: tuple[np.ndarray, np.ndarray] | None = None

    def window(self, t: int) -> Window:
        N = self.problem.n_steps
        return Window(t, min(self.horizon, N - t), N)

    def _terminal(self, window: Window, provided: TerminalCost | None) -> TerminalCost | None:
        if not window.reaches_end:
            if provided is None:
                raise ValueError(f"provider {self.provider.name!r} gave no terminal cost for window {window}")
            return provided
        if self.mode == "soft":
            return TerminalCost(self.problem.goal, self.scenario.mpc.end)
        return None  # hard: x_N = goal

    def solve(self, window: Window, X: np.ndarray, U: np.ndarray, terminal: TerminalCost | None) -> SCPResult:
        soft = self.mode == "soft"
        return solve_scp(
            self.scenario,
            self.problem,
            X,
            U,
            window=window,
            terminal=self._terminal(window, terminal),
            fuel_weight=self.scenario.mpc.fuel if soft else 1.0,
            soft_equalities=soft,
            backend=self.backend,
        )

    def plan(self, t: int, x: np.ndarray) -> StepPlan:
        """Warm start + SCP for the window at step t from the measured state x."""
        window = self.window(t)
        t0 = time.perf_counter()
        ws = self.provider.warm_start(window, x)
        t1 = time.perf_counter()
        if ws.X.shape != (window.length + 1, len(x)) or ws.U.shape[0] != window.length:
            raise ValueError(
                f"{self.provider.name}: warm start shapes {ws.X.shape}, {ws.U.shape} do not fit window {window}"
            )
        res = self.solve(window, ws.X, ws.U, ws.terminal)
        t2 = time.perf_counter()
        if res.success:
            X, U, fallback = res.X, res.U, False
        elif self._plan is not None and len(self._plan[1]) > 1:
            X, U, fallback = self._plan[0][1:], self._plan[1][1:], True
        else:
            X, U, fallback = ws.X, ws.U, True
        X = np.array(X, dtype=np.float64)
        X[0] = x
        target = None if ws.terminal is None else ws.terminal.target
        return StepPlan(
            U[0].copy(), X, np.array(U, dtype=np.float64), t1 - t0, t2 - t1, res.iterations, fallback, target
        )

    def observe(self, plan: StepPlan, u: np.ndarray, x_next: np.ndarray) -> None:
        """Record the executed control (which may differ from the plan's, e.g. in DAgger) and the next state."""
        self._plan = (plan.X, plan.U)
        self.provider.observe(u, x_next, plan.X, plan.U)


def episode_metrics(
    scenario: Scenario,
    problem: Problem,
    X: np.ndarray,
    U: np.ndarray,
    *,
    terminal_tol: float | None = None,
    path_tol: float = 1e-3,
    strict_keepout: bool = True,
) -> dict[str, float | int | bool]:
    """Feasibility of an executed trajectory: terminal error, keep-out violations, exact path violation. With
    ``strict_keepout`` any state inside a keep-out zone makes it infeasible; without, only a depth (part of the
    path violation) beyond ``path_tol`` does (the perturbed plant, whose disturbances no controller can undo)."""
    T = len(U)
    complete = T == problem.n_steps
    err = float(np.linalg.norm(X[-1] - problem.goal)) if complete else float("nan")
    koz = int(np.sum(scenario.violations(problem, X)))
    path = scenario.path_violation(problem, X, U, Window(0, T, problem.n_steps)) if T else 0.0
    tol = scenario.terminal_tol if terminal_tol is None else terminal_tol
    feasible = (koz == 0 or not strict_keepout) and path <= path_tol and (not complete or err <= tol)
    return {
        "terminal_error": err,
        "keepout_violations": koz,
        "path_violation": float(path),
        "complete": complete,
        "feasible": bool(feasible),
    }


def target_change(scenario: Scenario, targets: list[np.ndarray | None]) -> float:
    """Mean ‖(x̄_t − x̄_{t−1}) / state_scale‖₂ over consecutive steps that both have a terminal target."""
    n = scenario.state_dim
    scale = np.asarray(scenario.state_scale, dtype=np.float64) if len(scenario.state_scale) == n else np.ones(n)
    d = [np.linalg.norm((b - a) / scale) for a, b in itertools.pairwise(targets) if a is not None and b is not None]
    return float(np.mean(d)) if d else float("nan")


def run_mpc(
    scenario: Scenario,
    problem: Problem,
    provider: Provider,
    horizon: int,
    *,
    rel_cost: float,
    mode: Mode = "soft",
    max_steps: int | None = None,
    backend: str = "auto",
    terminal_tol: float | None = None,
    plant: PlantNoise | None = None,
    plant_seed: int = 0,
) -> Episode:
    """Run receding-horizon control from x0 for N steps (or ``max_steps``) on the exact dynamics, or on a perturbed
    plant (``plant``, disturbances seeded by ``plant_seed``: same seed, same disturbances).

    ``rel_cost`` is J_REL of the open-loop REL solution: the lower bound of the metrics and the TTO conditioning
    (rtg_0 = −J_REL)."""
    N = problem.n_steps
    T = N if max_steps is None else min(max_steps, N)
    provider.reset(scenario, problem, rel_cost)
    ctrl = MPCController(scenario, problem, provider, horizon, mode=mode, backend=backend)
    sim = Plant(scenario, plant)
    sim.reset(plant_seed)
    x = problem.x0.copy()
    X, U = [x], []
    warm, solve, iters = np.zeros(T), np.zeros(T), np.zeros(T, dtype=int)
    targets: list[np.ndarray | None] = []
    fallbacks = 0
    for t in range(T):
        plan = ctrl.plan(t, x)
        x = sim.step(problem, t, x, plan.u)
        ctrl.observe(plan, plan.u, x)
        X.append(x)
        U.append(plan.u)
        warm[t], solve[t], iters[t] = plan.warm_time, plan.solve_time, plan.iterations
        targets.append(plan.target)
        fallbacks += plan.fallback
    Xa, Ua = np.stack(X), np.stack(U) if U else np.zeros((0, scenario.control_dim))
    perturbed = plant is not None and not plant.nominal
    m = episode_metrics(
        scenario,
        problem,
        Xa,
        Ua,
        terminal_tol=terminal_tol,
        path_tol=plant.path_tol(scenario) if plant is not None and perturbed else 1e-3,
        strict_keepout=not perturbed,
    )
    return Episode(
        method=provider.name,
        horizon=horizon,
        X=Xa,
        U=Ua,
        cost=scenario.cost(Ua),
        rel_cost=float(rel_cost),
        step_times=warm + solve,
        warm_times=warm,
        solve_times=solve,
        iterations=iters,
        fallbacks=fallbacks,
        terminal_error=float(m["terminal_error"]),
        keepout_violations=int(m["keepout_violations"]),
        path_violation=float(m["path_violation"]),
        complete=bool(m["complete"]),
        feasible=bool(m["feasible"]),
        target_change=target_change(scenario, targets),
        plant="perturbed" if perturbed else "nominal",
    )
