"""Warm-start and terminal-target providers of the receding-horizon loop (paper §V-C, fact sheet §5.2).

A provider fills the window [t, t+H) with a warm start in the *optimisation* representation (states (H+1, n) whose
first row is the measured state, controls (H, m)) and, for windows that stop before the end, the terminal cost:

* ``RELProvider`` (REL-MPC): REL over the whole remaining horizon [t, N) from x_t, truncated to the window; the
  terminal target x̄ is the REL state at t+H (weights ``mpc.terminal``).
* ``DISTProvider`` (DIST-MPC): REL over the window only, with the distance-to-goal terminal cost diag(``mpc.dist``).
* ``TTOProvider`` (TTO-MPC / FT-TTO-MPC): an H-step transformer rollout from the running ``RolloutContext``
  (conditioned once on rtg_0 = −J_REL, ctg_0 = 0); the context is advanced with every executed action and measured
  state, so its KV cache is extended, never recomputed. x̄ = the predicted state at t+H.
* ``ShiftProvider`` (the DAgger expert): the previous plan shifted by one step (first row replaced by the measured
  state), starting from a given plan; it makes the full-horizon expert cheap.

Terminal index: our terminal term penalises x_{t+H}, the state *after* the last window control (the window has
H+1 states). The reference penalised x_{t+H−1}, the last state *before* the last control, which leaves the last
control of every window free of the terminal term.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from ttompc.scenarios.base import Problem, Scenario, Window
from ttompc.solvers.scp import TerminalCost, solve_rel

if TYPE_CHECKING:
    from ttompc.policy import Planner, RolloutContext


@dataclass
class WarmStart:
    """A window's initial guess (optimisation representation) and its terminal cost (None if the window reaches
    the end: the loop then imposes the end condition)."""

    X: np.ndarray  # (H+1, n), X[0] = measured state
    U: np.ndarray  # (H, m)
    terminal: TerminalCost | None


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


class RELProvider:
    """REL-MPC: full remaining-horizon REL, truncated; terminal target = REL state at t+H."""

    name = "REL-MPC"

    def __init__(self, backend: str = "auto") -> None:
        self.backend = backend

    def reset(self, scenario: Scenario, problem: Problem, rel_cost: float) -> None:
        self.scenario, self.problem = scenario, problem

    def warm_start(self, window: Window, x: np.ndarray) -> WarmStart:
        sc, p = self.scenario, self.problem
        rest = Window(window.start, p.n_steps - window.start, p.n_steps)
        rel = solve_rel(sc, p, window=rest, x_start=x, backend=self.backend)
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


class TTOProvider:
    """TTO-MPC: H-step rollout from a persistent rollout context (one per episode, KV cache reused)."""

    def __init__(
        self, planner: Planner, name: str = "TTO-MPC", *, use_cache: bool = True, clipped: bool = True
    ) -> None:
        self.planner, self.name, self.use_cache, self.clipped = planner, name, use_cache, clipped
        self.context: RolloutContext | None = None

    def reset(self, scenario: Scenario, problem: Problem, rel_cost: float) -> None:
        if scenario.name != self.planner.scenario.name:
            raise ValueError(f"model was trained on {self.planner.scenario.name!r}, not {scenario.name!r}")
        self.scenario, self.problem = scenario, problem
        self.context = self.planner.context([problem], rtg0=-rel_cost, ctg0=0.0, use_cache=self.use_cache)

    def _sync(self) -> None:
        if self.planner.device.type == "cuda":
            import torch

            torch.cuda.synchronize()

    def warm_start(self, window: Window, x: np.ndarray) -> WarmStart:
        if self.context is None or self.context.t != window.start:
            raise RuntimeError(f"rollout context is at step {getattr(self.context, 't', None)}, not {window.start}")
        res = self.context.rollout(window.length, clipped=self.clipped)
        self._sync()
        S = res.states[0].double().cpu().numpy()
        X = self.scenario.from_model_states(self.problem, S, start=window.start)
        X[0] = x  # the measured state, exactly (the context holds it in the model dtype)
        U = res.actions[0].double().cpu().numpy()
        return WarmStart(X, U, _terminal(window, X[-1], self.scenario.mpc.terminal))

    def observe(self, u: np.ndarray, x_next: np.ndarray, plan_X: np.ndarray, plan_U: np.ndarray) -> None:
        assert self.context is not None
        k = self.context.t + 1
        s_next = self.scenario.to_model_states(self.problem, np.asarray(x_next)[None], start=k)[0]
        self.context.advance(np.asarray(u)[None], s_next[None])
        self._sync()


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
