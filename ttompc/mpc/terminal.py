"""The terminal term of the plan-tracking providers (TTO-MPC, PLAN-ONCE, ORACLE-MPC; the terminal cost
‖x_{t+H} − x̄‖_P of paper §V, Eq. (8)): how a provider's window plan (a model rollout, an oracle) becomes the terminal
cost of a window that stops early. One class per kind, registered in ``TERMINALS`` under the name that
``MPCSettings.terminal`` takes.

A kind declares, as class attributes and class methods, what the layers above need of it:

* ``name``: its ``MPCSettings.terminal`` value;
* ``refusal(planner)``: why a method with this model (None: a method without one) cannot use it, or None;
* ``departures(settings, scenario)``: the sentences a report lists under its table where the kind or its settings
  depart from the paper (``ttompc.mpc.departures``);
* ``rollouts``: whether DAgger's rollouts can run it (``ttompc.finetune.config.check_rollout_settings``);
* ``build(settings, blend, planner)``: one episode's term under ``settings``, the target blended by ``blend``;

and an instance, one per episode, is reset at the episode's start with its problem (``reset``) and called with each
window's plan (``__call__``). Adding a kind is a class here, its entry in ``TERMINALS`` and the presets that name it.

``target`` (the paper's, ``TargetFilter``): ‖diag(w)(x_{t+H} − x̄)‖₂ with x̄ the plan's state at t+H, or the robust
variant measured in ``docs/evaluation.md`` (the new target blended with the previous target shifted by one step,
``TerminalDesign.blend``), weighted by ``mpc.tracking`` on every component (``MPCSettings.track`` replaces it). That
weight must exceed the multiplier of the window's terminal constraint for a window to keep an exact plan
(``MPCWeights``); the paper's weight (``MPCWeights.target``) does not on the free-flyer and the quadrotor, so the
tracking weight (3 and 2 there) is a departure from the paper for TTO-MPC, which PLAN-ONCE and ORACLE-MPC share so
that they stay its ceilings.

``value`` and ``value+target`` price what finishing costs (a departure): the model's learned cost-to-go
V(x_{t+H}, t+H) at the window's end state, alone or beside the target pull. The value output's ``gauss_newton`` form
(``ttompc.policy.value``) gives J(x) = σ·½‖r(x)‖² with a positive semidefinite Gauss–Newton Hessian, so every SCP
iteration of a window pays the convex quadratic model of J about its reference end state (``StepValue.expand``; the
engine re-expands it per iteration), and the merit that accepts or rejects an iterate reads J itself. Every window
takes it: the Riccati kernel (free-flyer, quadrotor) as its dense terminal block, QOCO and Clarabel (RPOD's conic
windows, and any window sent to them) as a dense block in P with its linear term in q (``ttompc.solvers.objective``).
What remains refused is a model whose value output has no curvature (``refusal``).

Terminal index: the term penalises x_{t+H}, the state *after* the last window control (the window has H+1 states).
The reference penalised x_{t+H−1}, the last state *before* the last control, which leaves the last control of every
window free of the terminal term.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from ttompc.mpc.settings import MPCSettings, register_names
from ttompc.scenarios.base import Problem, Scenario, Window
from ttompc.solvers.scp import TerminalCost

if TYPE_CHECKING:
    from ttompc.policy import Planner
    from ttompc.policy.value import ValueExpansion, ValueModel


class TerminalTerm(ABC):
    """One episode's terminal term of a plan-tracking provider (module doc: what a kind declares)."""

    name: ClassVar[str]
    rollouts: ClassVar[bool] = True
    # the kind a method without a model runs instead (PLAN-ONCE, ORACLE-MPC beside a learned kind); None: the same
    without_model: ClassVar[str | None] = None

    @classmethod
    def refusal(cls, planner: Planner | None) -> str | None:
        """Why a method planning with ``planner`` (None: a method without a model) cannot use this kind; None: it
        can."""
        return None

    @classmethod
    def departures(cls, settings: MPCSettings, scenario: Scenario) -> list[str]:
        """Where this kind under ``settings`` departs from the paper on ``scenario``, one sentence each."""
        return []

    @classmethod
    @abstractmethod
    def build(cls, settings: MPCSettings, blend: float = 0.0, planner: Planner | None = None) -> TerminalTerm:
        """One episode's term under ``settings``, the target blended by ``blend`` (0: the paper's target)."""

    @abstractmethod
    def reset(self, scenario: Scenario, problem: Problem) -> None:
        """Start an episode of ``problem``."""

    @abstractmethod
    def __call__(self, scenario: Scenario, window: Window, X: np.ndarray) -> TerminalCost | None:
        """The terminal cost of ``window`` from the provider's window plan ``X`` (H+1, n); None when the window
        reaches the end (the loop imposes the end condition)."""


@dataclass(frozen=True)
class TerminalDesign:
    """How the ``target`` kind turns plans into targets.

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


class TargetFilter(TerminalTerm):
    """``target``, the paper's terminal term (module doc) under a ``TerminalDesign``; remembers the previous
    target for the blend."""

    name = "target"

    def __init__(self, design: TerminalDesign | None = None) -> None:
        self.design = design or TerminalDesign()
        self._forget()

    @classmethod
    def departures(cls, settings: MPCSettings, scenario: Scenario) -> list[str]:
        track = scenario.mpc.tracking if settings.track is None else settings.track
        if track == scenario.mpc.target:
            return []
        return [
            f"plan-tracking terminal weight {track:g} for TTO-MPC, PLAN-ONCE and ORACLE-MPC (the paper: "
            f"{scenario.mpc.target:g}, below the terminal multipliers of optimal plans; docs/evaluation.md)"
        ]

    @classmethod
    def build(cls, settings: MPCSettings, blend: float = 0.0, planner: Planner | None = None) -> TargetFilter:
        """The tracking weight ``settings.track`` on every component (None: the scenario's ``mpc.tracking``)."""
        return cls(TerminalDesign(blend, None if settings.track is None else (settings.track,)))

    def reset(self, scenario: Scenario, problem: Problem) -> None:
        self._forget()

    def _forget(self) -> None:
        """No previous target: the next one is the plan's own."""
        self._prev: np.ndarray | None = None
        self._prev_stop = -1

    def __call__(self, scenario: Scenario, window: Window, X: np.ndarray) -> TerminalCost | None:
        if window.reaches_end:
            self._forget()
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


class StepValue:
    """J(x) of one problem at one step: the value model's cost-to-go of an optimisation state x, with its local
    model (``ttompc.solvers.results.TerminalValue``)."""

    def __init__(self, model: ValueModel, goal: np.ndarray, M: np.ndarray, step: int) -> None:
        self.model, self.goal, self.M, self.step = model, goal, M, step

    def expand(self, x: np.ndarray) -> ValueExpansion:
        return self.model.expand(self.goal, self.M @ x, self.step, self.M)

    def __call__(self, x: np.ndarray) -> float:
        return self.expand(x).value


def model_map(scenario: Scenario, problem: Problem, step: int) -> np.ndarray:
    """The linear map (n, n) from an optimisation state at ``step`` to the model's representation (the identity,
    or RPOD's ROE -> RTN)."""
    n = scenario.state_dim
    return np.stack([scenario.to_model_states(problem, e[None], start=step)[0] for e in np.eye(n)], axis=1)


class ValueTerminal(TargetFilter):
    """``value+target``: the model's cost-to-go at the window's end plus the paper's target pull (module doc)."""

    name = "value+target"
    pull = True

    def __init__(self, planner: Planner, design: TerminalDesign | None = None) -> None:
        super().__init__(design)
        self.value_model = planner.value_model()
        self._goal = np.zeros(0)
        self._maps: dict[int, np.ndarray] = {}

    without_model = "target"  # PLAN-ONCE and ORACLE-MPC keep the paper's term

    @classmethod
    def refusal(cls, planner: Planner | None) -> str | None:
        if planner is None:
            return "a method without a model has no learned cost-to-go"
        if not planner.has_value or planner.model.cfg.value_form != "gauss_newton":
            return "needs a model whose value output has curvature (model.value_form: gauss_newton)"
        return None

    @classmethod
    def departures(cls, settings: MPCSettings, scenario: Scenario) -> list[str]:
        return [
            f"terminal {cls.name}: each window that stops early pays the model's learned cost-to-go of its end state "
            "(a convex local model per SCP iteration); the paper pulls toward the model's state with a fixed weight"
        ] + (TargetFilter.departures(settings, scenario) if cls.pull else [])

    @classmethod
    def build(cls, settings: MPCSettings, blend: float = 0.0, planner: Planner | None = None) -> ValueTerminal:
        assert planner is not None  # refusal() names it
        return cls(planner, TerminalDesign(blend, None if settings.track is None else (settings.track,)))

    def reset(self, scenario: Scenario, problem: Problem) -> None:
        super().reset(scenario, problem)
        self._problem, self._maps = problem, {}
        self._goal = scenario.model_goal(problem)

    def __call__(self, scenario: Scenario, window: Window, X: np.ndarray) -> TerminalCost | None:
        pulled = super().__call__(scenario, window, X)
        if pulled is None:
            return None
        k = window.stop
        if k not in self._maps:
            self._maps[k] = model_map(scenario, self._problem, k)
        weights = pulled.weights if self.pull else 0.0
        return TerminalCost(pulled.target, weights, value=StepValue(self.value_model, self._goal, self._maps[k], k))


class ValueOnlyTerminal(ValueTerminal):
    """``value``: the model's cost-to-go at the window's end alone (module doc)."""

    name = "value"
    pull = False


TERMINALS: dict[str, type[TerminalTerm]] = {
    kind.name: kind for kind in (TargetFilter, ValueTerminal, ValueOnlyTerminal)
}
register_names("terminal", TERMINALS)


def terminal_term(settings: MPCSettings, blend: float = 0.0, planner: Planner | None = None) -> TerminalTerm:
    """One episode's terminal term of the kind ``settings.terminal`` names (for a method without a model, the kind's
    ``without_model`` where it names one); raises ``ConfigError`` naming the setting when the kind cannot serve a
    method with ``planner`` (its ``refusal``)."""
    from ttompc.config import ConfigError

    kind = TERMINALS[settings.terminal]
    if planner is None and kind.without_model is not None:
        kind = TERMINALS[kind.without_model]
    why = kind.refusal(planner)
    if why is not None:
        raise ConfigError(f"terminal={settings.terminal}: {why}", f"use one of {sorted(TERMINALS)} that fits")
    return kind.build(settings, blend, planner)
