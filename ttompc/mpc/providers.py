"""Warm-start and terminal-target providers of the receding-horizon loop (paper §V-C; the terminal cost
‖x_{t+H} − x̄‖_P of §V, Eq. (8)).

A provider fills the window [t, t+H) with a warm start in the *optimisation* representation (states (H+1, n) whose
first row is the measured state, controls (H, m)) and, for windows that stop before the end, the terminal cost:

* ``RELProvider`` (REL-MPC): REL over the whole remaining horizon [t, N) from x_t, truncated to the window; the
  terminal target x̄ is the REL state at t+H (weights ``MPCWeights.target``).
* ``DISTProvider`` (DIST-MPC): REL over the window only, with the distance-to-goal terminal cost diag(``mpc.dist``).
* ``TTOProvider`` (TTO-MPC / FT-TTO-MPC) and its batching (``RolloutGroup``): ``ttompc.mpc.tto``.
* ``ShiftProvider`` (the DAgger expert): the previous plan shifted by one step (first row replaced by the measured
  state), starting from a given plan; it makes the full-horizon expert cheap.
* ``PlanProvider`` (PLAN-ONCE): one full-horizon plan (the open-loop SCP optimum, solved at t = 0) as warm start and
  terminal target of every window: "plan once, then track", no model, no re-planning. Perturbed, it is the
  noisy oracle of ``bench/tto_mpc_robustness.py`` (a stand-in for a model whose plans are off by a known amount).
* ``OracleProvider`` (ORACLE-MPC, the ceiling): the full remaining-horizon SCP optimum from the measured state
  (re-solved, warm-started from its own previous plan, whenever the state leaves the plan), as warm start and
  terminal target — what a perfect model could give.

Terminal targets of TTO-MPC and the plan providers are their terminal term's (``ttompc.mpc.terminal``: the paper's
target, the plan's state at t+H, or its robust variant), the same kind for all three so that PLAN-ONCE and ORACLE-MPC
stay TTO-MPC's ceilings.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ttompc.mpc.settings import Role
from ttompc.mpc.terminal import TargetFilter, TerminalTerm
from ttompc.scenarios.base import Problem, Scenario, Window
from ttompc.solvers.scp import SCPOptions, SCPProblem, SCPResult, TerminalCost, solve_problem, solve_rel, solve_scp


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

    name: str  # the report name of the method it serves (``Method.providers`` passes it; standalone: the class's)
    role: Role  # what its plans are: the input of the RTI and end-shift rules (``MPCSettings.rti_for``, ``shift_for``)

    def reset(self, scenario: Scenario, problem: Problem, rel_cost: float) -> None:
        """Start an episode; ``rel_cost`` is J_REL of the open-loop REL solution (TTO conditioning)."""

    def warm_start(self, window: Window, x: np.ndarray) -> WarmStart:
        """Warm start of ``window`` from the measured state ``x`` at ``window.start``."""

    def observe(self, u: np.ndarray, x_next: np.ndarray, plan_X: np.ndarray, plan_U: np.ndarray) -> float | None:
        """The executed control, the measured next state and the solved window plan (for shifting). The loop times
        the call into the step that plans from ``x_next``. Returns None, or the seconds of the call spent on work
        shared with other episodes run in lockstep (a ``RolloutGroup``'s batched context advance; 0.0 for a sharing
        provider whose call only queued its part), which the loop splits evenly among the episodes whose providers
        return a number (``run_mpc_batch``)."""


def _terminal(window: Window, target: np.ndarray, weights: np.ndarray | float) -> TerminalCost | None:
    """The soft terminal term of a window that stops early; None when it reaches the end (the loop decides)."""
    return None if window.reaches_end else TerminalCost(target=target, weights=np.asarray(weights, dtype=np.float64))


class RemainingREL:
    """REL over the whole remaining horizon [t, N) from the measured state, each solve started from the last one's
    plan shifted to t (``solve_rel(guess=...)``) instead of the straight line: the same relaxation from a nearby
    start, about half the time (measured in docs/benchmarks.md, MPC section). The shift spans the steps it was not
    asked for (a controller that reused its plan skips its provider). REL-MPC plans with it; TTO-MPC's
    ``rtg_mode="reanchor"`` reads its cost."""

    def __init__(self, backend: str = "auto") -> None:
        self.backend = backend
        self._rel: tuple[int, np.ndarray, np.ndarray] | None = None  # (start step, X, U) of the last solve

    def reset(self) -> None:
        self._rel = None

    def __call__(self, scenario: Scenario, problem: Problem, t: int, x: np.ndarray) -> SCPResult:
        rest = Window(t, problem.n_steps - t, problem.n_steps)
        guess = None
        if self._rel is not None and 0 < t - self._rel[0] < len(self._rel[2]):
            start, X, U = self._rel
            guess = (X[t - start :], U[t - start :])
        rel = solve_rel(scenario, problem, window=rest, x_start=x, guess=guess, backend=self.backend)
        self._rel = (t, rel.X, rel.U) if rel.success else None
        return rel


class RELProvider:
    """REL-MPC: full remaining-horizon REL (``RemainingREL``), truncated; terminal target = REL state at t+H
    (weight ``MPCWeights.target``, the paper's)."""

    role: Role = "baseline"

    def __init__(self, backend: str = "auto", *, name: str = "") -> None:
        self.name, self.backend = name or type(self).__name__, backend
        self.rel = RemainingREL(backend)

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
        return WarmStart(X, U, _terminal(window, X[-1], sc.mpc.target))

    def observe(self, u: np.ndarray, x_next: np.ndarray, plan_X: np.ndarray, plan_U: np.ndarray) -> None:
        return None


class DISTProvider:
    """DIST-MPC: REL on the window only, terminal cost ‖diag(dist)(x_{t+H} − goal)‖₂ (no look-ahead)."""

    role: Role = "baseline"

    def __init__(self, backend: str = "auto", *, name: str = "") -> None:
        self.name, self.backend = name or type(self).__name__, backend

    def reset(self, scenario: Scenario, problem: Problem, rel_cost: float) -> None:
        self.scenario, self.problem = scenario, problem

    def warm_start(self, window: Window, x: np.ndarray) -> WarmStart:
        sc, p = self.scenario, self.problem
        terminal = _terminal(window, p.goal, np.asarray(sc.mpc.dist, dtype=np.float64))
        if terminal is None:  # the window reaches the end: the REL carries the end condition itself
            terminal_rel = TerminalCost(p.goal, sc.mpc.end)
        else:
            terminal_rel = terminal
        rel_problem = SCPProblem(sc, p, window, terminal_rel, obstacles=False, soft=True)  # REL, soft mode
        rel = solve_scp(rel_problem, *sc.initial_guess(p, window, x), SCPOptions(backend=self.backend))
        X, U = (rel.X.copy(), rel.U.copy()) if rel.success else sc.initial_guess(p, window, x)
        X[0] = x
        return WarmStart(X, U, terminal)

    def observe(self, u: np.ndarray, x_next: np.ndarray, plan_X: np.ndarray, plan_U: np.ndarray) -> None:
        return None


class ShiftProvider:
    """The previous plan shifted by one step (DAgger expert); the first plan comes from ``reset_plan``."""

    role: Role = "expert"

    def __init__(self) -> None:
        self.name = type(self).__name__
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
        return WarmStart(X, U, _terminal(window, X[-1], self.scenario.mpc.target))

    def observe(self, u: np.ndarray, x_next: np.ndarray, plan_X: np.ndarray, plan_U: np.ndarray) -> None:
        self.X, self.U = plan_X[1:], plan_U[1:]


class PlanProvider:
    """PLAN-ONCE: a fixed full-horizon plan (given, or the open-loop SCP optimum solved at t = 0) as warm start and
    terminal target of every window through ``terminal`` (None: the paper's target). ``window_plan`` is the plan a
    window gets (``bench/tto_mpc_robustness.py`` perturbs it: the noisy oracle)."""

    role: Role = "baseline"

    def __init__(
        self,
        plan: tuple[np.ndarray, np.ndarray] | None = None,
        *,
        name: str = "",
        terminal: TerminalTerm | None = None,
        backend: str = "auto",
    ) -> None:
        self.name, self.backend = name or type(self).__name__, backend
        self._given = plan
        self.target = terminal if terminal is not None else TargetFilter()

    def reset(self, scenario: Scenario, problem: Problem, rel_cost: float) -> None:
        self.scenario, self.problem = scenario, problem
        self.X, self.U = self._given if self._given is not None else full_horizon_plan(scenario, problem, self.backend)
        self.target.reset(scenario, problem)

    def window_plan(self, window: Window) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the plan's states (H+1, n) and controls (H, m) over ``window``."""
        t, H = window.start, window.length
        return self.X[t : t + H + 1].copy(), self.U[t : t + H].copy()

    def warm_start(self, window: Window, x: np.ndarray) -> WarmStart:
        X, U = self.window_plan(window)
        X[0] = x
        return WarmStart(X, U, self.target(self.scenario, window, X))

    def observe(self, u: np.ndarray, x_next: np.ndarray, plan_X: np.ndarray, plan_U: np.ndarray) -> None:
        return None


def full_horizon_plan(scenario: Scenario, problem: Problem, backend: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """The open-loop SCP optimum warm-started by REL (falls back to the REL solution if the SCP fails)."""
    rel, scp = solve_problem(scenario, problem, backend=backend)
    best = scp if scp is not None and scp.success else rel
    return best.X, best.U


class RemainingOptimum:
    """The full remaining-horizon SCP optimum [t, N) from a measured state, tracked along an episode: the first plan
    is given (or REL → SCP from x_0); at each later call the previous plan is moved on to step t, and re-solved from
    it (SCP, first row replaced by the measured state) whenever the measured state is off it by more than
    ``REPLAN_TOL`` (in units of the scenario's ``state_scale``, ∞-norm). On the exact plant the optimum's tail stays
    optimal (principle of optimality), so an episode on it re-solves rarely; on a perturbed plant nearly every step.
    ``replans`` counts the re-solves. ORACLE-MPC plans with it; TTO-MPC's ``rtg_mode="oracle"`` reads its cost."""

    REPLAN_TOL = 1e-3

    def __init__(self, plan: tuple[np.ndarray, np.ndarray] | None = None, backend: str = "auto") -> None:
        self._given, self.backend = plan, backend

    def reset(self, scenario: Scenario, problem: Problem) -> None:
        self.scenario, self.problem = scenario, problem
        X, U = self._given if self._given is not None else full_horizon_plan(scenario, problem, self.backend)
        self.X, self.U = np.array(X, dtype=np.float64), np.array(U, dtype=np.float64)
        self.start = 0  # the step of self.X[0]
        self._scale = scenario.state_units()
        self.replans = 0

    def __call__(self, t: int, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The optimum's plan over [t, N) from ``x``: states (N − t + 1, n) with X[0] = x, controls (N − t, m)."""
        if not self.start <= t < self.start + len(self.U):
            raise ValueError(f"the remaining optimum is at step {self.start}, asked for step {t}")
        self.X, self.U, self.start = self.X[t - self.start :], self.U[t - self.start :], t
        p = self.problem
        if np.max(np.abs(x - self.X[0]) / self._scale) > self.REPLAN_TOL:
            X0 = self.X.copy()
            X0[0] = x
            rest = Window(t, p.n_steps - t, p.n_steps)
            res = solve_scp(SCPProblem(self.scenario, p, rest), X0, self.U, SCPOptions(backend=self.backend))
            self.replans += 1
            if res.success:
                self.X, self.U = res.X, res.U
        X = self.X.copy()
        X[0] = x
        return X, self.U.copy()


class OracleProvider:
    """ORACLE-MPC (the ceiling): the full remaining-horizon SCP optimum from the measured state
    (``RemainingOptimum``; the first plan given, or REL → SCP) as warm start and terminal target through ``terminal``
    (None: the paper's target) — what a perfect model could give. ``replans`` counts its re-solves."""

    role: Role = "baseline"

    def __init__(
        self,
        plan: tuple[np.ndarray, np.ndarray] | None = None,
        *,
        name: str = "",
        backend: str = "auto",
        terminal: TerminalTerm | None = None,
    ) -> None:
        self.name = name or type(self).__name__
        self.optimum = RemainingOptimum(plan, backend)
        self.target = terminal if terminal is not None else TargetFilter()

    @property
    def replans(self) -> int:
        return self.optimum.replans

    def reset(self, scenario: Scenario, problem: Problem, rel_cost: float) -> None:
        self.scenario = scenario
        self.optimum.reset(scenario, problem)
        self.target.reset(scenario, problem)

    def warm_start(self, window: Window, x: np.ndarray) -> WarmStart:
        X, U = self.optimum(window.start, x)
        X, U = X[: window.length + 1], U[: window.length]
        return WarmStart(X, U, self.target(self.scenario, window, X))

    def observe(self, u: np.ndarray, x_next: np.ndarray, plan_X: np.ndarray, plan_U: np.ndarray) -> None:
        return None
