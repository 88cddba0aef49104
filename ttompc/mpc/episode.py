"""A closed-loop episode's record (``Episode``), built step by step (``EpisodeTrace``, from each step's ``StepPlan``)
by the receding-horizon loop (``ttompc.mpc.loop``), its feasibility (``episode_metrics``) and its relative cost
increment over J_REL (``rel_increment``).

Episodes count as reaching the goal when they ran all N steps and ‖x_N − goal‖₂ <= scenario.terminal_tol: an
episode cut short (``max_steps`` < N, a smoke run) is ``complete`` False and never ``feasible``, whatever its cost
(it has not reached the goal; the reports count it among the failures and say how many were cut).

A goal miss is not the soft end penalty's: tracking an exact plan ends on the goal once the tracking weight exceeds
the multiplier of the window's terminal constraint (``MPCWeights.track``); a plan that lags (REL-MPC at H = 10,
docs/design.md) brings the goal into the window when the control bound no longer lets it be reached
(``MPCSettings.end_horizon``). Plan consistency is recorded per episode: ``target_change`` is the mean over
consecutive steps of ‖(x̄_t − x̄_{t−1}) / state_scale‖₂, the change of the terminal target between MPC steps in units
of the scenario's characteristic magnitudes (a consistent plan moves it by about one step of motion; a jittering one
by much more).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from ttompc.mpc.plant import PlantNoise
from ttompc.scenarios.base import Problem, Scenario, Window


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
    soft_end: bool = False  # hard mode: the goal was out of reach, the window used the soft end term
    reused: bool = False  # the previous plan's tail, neither provider nor solver called (``ttompc.mpc.loop`` doc)
    converged: bool = False  # the SCP met its stopping rule (a fixed point), or the tail of such a plan: reusable


@dataclass
class Episode:
    """A closed-loop run: executed trajectory (T+1 states, T controls; T = N unless ``max_steps``) and metrics."""

    method: str
    horizon: int
    X: np.ndarray
    U: np.ndarray
    cost: float  # Σ c(u) of the executed controls
    rel_cost: float  # J_REL of the open-loop REL solution (lower bound of the full problem)
    step_times: np.ndarray  # (T,) observe + warm start + solve per step (s): measured state to control (loop doc)
    observe_times: np.ndarray  # (T,) the observe of the previous step's outcome (0 at t = 0)
    warm_times: np.ndarray
    solve_times: np.ndarray
    iterations: np.ndarray  # (T,) SCP iterations per step (all the step's window solves; 0 for a reused plan)
    fallbacks: int
    terminal_error: float  # ‖x_N − goal‖₂ (nan for truncated episodes)
    keepout_violations: int  # states of the executed trajectory inside a keep-out zone
    path_violation: float  # largest exact path-constraint violation (keep-out depth, bounds, ...)
    complete: bool  # ran all N steps
    feasible: bool  # complete, no keep-out violation, path violation ≤ tol and terminal error ≤ tol
    target_change: float = float("nan")  # plan consistency (module doc); nan without two consecutive targets
    plant: str = "nominal"  # "nominal" or "perturbed"
    soft_ends: int = 0  # hard mode: steps whose end window fell back to the soft end term (goal out of reach)
    reuses: int = 0  # steps that applied the previous plan's tail (plan reuse, loop doc)
    rti: bool | str = False  # real-time iteration, one subproblem per step: in every window, "end" ones, none

    def summary(self) -> dict[str, float | int | str | bool]:
        """Flat per-episode metrics (a run's row in the reports): the fields above, with the arrays reduced to
        ``mean_step_time``/``max_step_time`` (s), ``mean_iterations`` (SCP iterations per step, a reused step 0)
        and ``mean_iterations_solved`` (per step that ran the window SCP, i.e. not reused; nan if none did)."""
        solved = len(self.iterations) - self.reuses
        return {
            "method": self.method,
            "horizon": self.horizon,
            "cost": self.cost,
            "rel_cost": self.rel_cost,
            "steps": len(self.U),
            "mean_step_time": float(np.mean(self.step_times)) if len(self.step_times) else float("nan"),
            "max_step_time": float(np.max(self.step_times)) if len(self.step_times) else float("nan"),
            "mean_iterations": float(np.mean(self.iterations)) if len(self.iterations) else float("nan"),
            "mean_iterations_solved": float(np.sum(self.iterations) / solved) if solved else float("nan"),
            "fallbacks": self.fallbacks,
            "terminal_error": self.terminal_error,
            "keepout_violations": self.keepout_violations,
            "path_violation": self.path_violation,
            "complete": self.complete,
            "feasible": self.feasible,
            "target_change": self.target_change,
            "plant": self.plant,
            "soft_ends": self.soft_ends,
            "reuses": self.reuses,
            "rti": self.rti,
        }


def episode_metrics(
    scenario: Scenario,
    problem: Problem,
    X: np.ndarray,
    U: np.ndarray,
    *,
    path_tol: float = 1e-3,
    strict_keepout: bool = True,
) -> dict[str, float | int | bool]:
    """Feasibility of an executed trajectory: complete (all N steps: a truncated one is never feasible), terminal
    error (within ``scenario.terminal_tol``; nan when truncated), keep-out violations, exact path violation. With
    ``strict_keepout`` any state inside a keep-out zone makes it infeasible; without, only a depth (part of the
    path violation) beyond ``path_tol`` does (the perturbed plant, whose disturbances no controller can undo)."""
    T = len(U)
    complete = T == problem.n_steps
    err = float(np.linalg.norm(X[-1] - problem.goal)) if complete else float("nan")
    koz = int(np.sum(scenario.violations(problem, X)))
    path = scenario.path_violation(problem, X, U, Window(0, T, problem.n_steps)) if T else 0.0
    feasible = complete and (koz == 0 or not strict_keepout) and path <= path_tol and err <= scenario.terminal_tol
    return {
        "terminal_error": err,
        "keepout_violations": koz,
        "path_violation": float(path),
        "complete": complete,
        "feasible": bool(feasible),
    }


def rel_increment(cost: float, rel_cost: float, feasible: bool) -> float:
    """The relative cost increment (J − J_REL)/J_REL of an episode of cost ``cost`` on a problem whose open-loop REL
    solution costs ``rel_cost``: nan when the episode is infeasible (its cost means nothing, module doc) or J_REL is
    missing (nan: no REL solve, e.g. an episode reset without one) or not a positive finite cost."""
    if not feasible or not (np.isfinite(rel_cost) and rel_cost > 0):
        return float("nan")
    return float((cost - rel_cost) / rel_cost)


def target_change(scenario: Scenario, targets: list[np.ndarray | None]) -> float:
    """Mean ‖(x̄_t − x̄_{t−1}) / state_scale‖₂ over consecutive steps that both have a terminal target."""
    scale = scenario.state_units()
    d = [np.linalg.norm((b - a) / scale) for a, b in itertools.pairwise(targets) if a is not None and b is not None]
    return float(np.mean(d)) if d else float("nan")


class EpisodeTrace:
    """What the steps of one episode of at most ``T`` steps from ``x0`` record (``record``: the plan that acted and
    the measured next state; ``observed``: the observe time charged to each step), until ``episode``."""

    def __init__(self, x0: np.ndarray, T: int) -> None:
        self.X: list[np.ndarray] = [x0]
        self.U: list[np.ndarray] = []
        self.warm, self.solve, self.observed = np.zeros(T), np.zeros(T), np.zeros(T)
        self.iterations = np.zeros(T, dtype=int)
        self.targets: list[np.ndarray | None] = []
        self.fallbacks = self.soft_ends = self.reuses = 0

    def record(self, t: int, plan: StepPlan, x_next: np.ndarray) -> None:
        """Step t applied ``plan.u`` and measured ``x_next``."""
        self.X.append(x_next)
        self.U.append(plan.u)
        self.warm[t], self.solve[t], self.iterations[t] = plan.warm_time, plan.solve_time, plan.iterations
        self.targets.append(plan.target)
        self.fallbacks += plan.fallback
        self.soft_ends += plan.soft_end
        self.reuses += plan.reused

    def episode(
        self,
        scenario: Scenario,
        problem: Problem,
        method: str,
        horizon: int,
        rel_cost: float,
        plant: PlantNoise | None,
        rti: bool | str,
    ) -> Episode:
        """The finished episode of ``method`` at ``horizon`` on ``problem`` (J_REL ``rel_cost``) on ``plant`` (None or
        nominal: the exact dynamics; perturbed: feasible within the plant's ``path_tol``, keep-out depth included)."""
        perturbed = plant is not None and not plant.nominal
        Xa = np.stack(self.X)
        Ua = np.stack(self.U) if self.U else np.zeros((0, scenario.control_dim))
        path_tol = plant.path_tol(scenario) if plant is not None and perturbed else 1e-3
        m = episode_metrics(scenario, problem, Xa, Ua, path_tol=path_tol, strict_keepout=not perturbed)
        return Episode(
            method=method,
            horizon=horizon,
            X=Xa,
            U=Ua,
            cost=scenario.cost(Ua),
            rel_cost=float(rel_cost),
            step_times=self.observed + self.warm + self.solve,
            observe_times=self.observed,
            warm_times=self.warm,
            solve_times=self.solve,
            iterations=self.iterations,
            fallbacks=self.fallbacks,
            terminal_error=float(m["terminal_error"]),
            keepout_violations=int(m["keepout_violations"]),
            path_violation=float(m["path_violation"]),
            complete=bool(m["complete"]),
            feasible=bool(m["feasible"]),
            target_change=target_change(scenario, self.targets),
            plant="perturbed" if perturbed else "nominal",
            soft_ends=self.soft_ends,
            reuses=self.reuses,
            rti=rti,
        )
