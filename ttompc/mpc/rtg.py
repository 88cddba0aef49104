"""The reward-to-go TTO-MPC feeds its model in closed loop (``MPCSettings.rtg_mode``): one class per mode, registered
in ``RTG_MODES`` under its name, the one list that settings, providers and reports read.

A mode declares, as class attributes, what the layers above need of it:

* ``name``: its ``rtg_mode`` value, and ``paper``: whether it is the paper's (any other is listed among a report's
  departures, ``departures``, and names its methods "...[rtg=NAME]", ``label``);
* ``needs_value``: it reads the model's value output (``Planner.has_value``), and ``fallback``: the mode a model
  without one runs instead (``for_model``; None: such a model is refused with a ``ConfigError``);
* ``rollouts``: whether DAgger's rollouts can run it (``ttompc.finetune.config.check_rollout_settings``);

and an instance, one per episode (its ``TTOProvider``'s), is reset at the episode's start (``reset``) and gives the
value to feed at step t (``__call__``; None: the context's running value). The provider clips every value to the range
training rows' rtg lie in (``TTOProvider.conditioning``). Adding a mode is a class here, its entry in ``RTG_MODES``
and the presets that name it.

Training rows hold rtg_t = −Σ_(τ≥t) c(u_τ), never above 0. The modes:

* ``running`` (the paper, the default): rtg_t = rtg_0 + the cost executed so far (the context's own ledger). Closed
  loop the executed cost soon exceeds J_REL and rtg_t turns positive, where no training row lives.
* ``reanchor``: rtg_t = −κ·J_REL(t), the REL cost of the remaining horizon [t, N) from the measured state (one
  ``RemainingREL`` per step, as REL-MPC solves; its time counts in the warm start); the running value where that REL
  fails.
* ``value``: rtg_t = −V(x_t, t), the model's own value output (``Planner.cost_to_go``: the learned cost-to-go of an
  optimal plan from the measured state). A model without a value output (every bundle from before it) runs
  ``running``, the paper's ledger, and its methods are named so (the zoo's cards report such a parent beside its
  value model under ``protocol=recommended``).
* ``oracle`` (a diagnostic, the ceiling of ``value``): rtg_t = −J*(x_t, t), the cost of the full remaining-horizon SCP
  optimum from the measured state (``RemainingOptimum``, from the open-loop optimum given or REL → SCP at t = 0; its
  solves count in the warm start).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from ttompc.mpc.providers import RemainingOptimum, RemainingREL
from ttompc.scenarios.base import Problem, Scenario

if TYPE_CHECKING:
    from ttompc.mpc.tto import TTOProvider
    from ttompc.policy import Planner


class RTGFeed(ABC):
    """One episode's reward-to-go under one mode (module doc: what a mode declares)."""

    name: ClassVar[str]
    paper: ClassVar[bool] = False
    needs_value: ClassVar[bool] = False
    fallback: ClassVar[str | None] = None
    rollouts: ClassVar[bool] = True

    def __init__(self, backend: str = "auto", plan: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """``backend``: the solver backend of the mode's own solves; ``plan``: the episode's open-loop optimum where
        the mode needs one (None: solved at ``reset``)."""
        self.backend = backend

    @classmethod
    def for_model(cls, planner: Planner) -> type[RTGFeed]:
        """The mode ``planner`` runs under this one: this one, or for a model without the value output it needs its
        declared ``fallback``; raises ``ConfigError`` naming the setting when there is none."""
        from ttompc.config import ConfigError

        if not cls.needs_value or planner.has_value:
            return cls
        if cls.fallback is None:
            raise ConfigError(
                f"rtg_mode={cls.name} needs a model with a value output (model.value_width > 0); this one has none",
                "use protocol=paper (rtg_mode=running, the paper's ledger) or a model with a value output",
            )
        return RTG_MODES[cls.fallback]

    @classmethod
    def label(cls) -> str:
        """What a method fed this mode adds to its name: nothing for the paper's, else "[rtg=NAME]"."""
        return "" if cls.paper else f"[rtg={cls.name}]"

    @classmethod
    def departures(cls) -> list[str]:
        """The sentence a report lists among its departures from the paper (none for the paper's mode)."""
        if cls.paper:
            return []
        return [f"reward-to-go fed in closed loop: {cls.name} (the paper: the running rtg_0 + executed cost)"]

    def reset(self, scenario: Scenario, problem: Problem) -> None:  # noqa: B027 (most modes keep no state)
        """Start an episode of ``problem``."""

    @abstractmethod
    def __call__(self, tto: TTOProvider, t: int) -> float | None:
        """The rtg to feed ``tto``'s model at step t from its measured state ``tto.x`` (unclipped; None: the
        context's running value)."""


class RunningRTG(RTGFeed):
    """``running``: the paper's ledger (module doc)."""

    name, paper = "running", True

    def __call__(self, tto: TTOProvider, t: int) -> float | None:
        return None


class ReanchorRTG(RTGFeed):
    """``reanchor``: −κ·J_REL of the remaining horizon from the measured state (module doc)."""

    name = "reanchor"

    def __init__(self, backend: str = "auto", plan: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        super().__init__(backend, plan)
        self.rel = RemainingREL(backend)

    def reset(self, scenario: Scenario, problem: Problem) -> None:
        self.rel.reset()

    def __call__(self, tto: TTOProvider, t: int) -> float | None:
        if t > 0:
            rel = self.rel(tto.scenario, tto.problem, t, tto.x)
            if rel.success:
                return -tto.rtg_scale * rel.cost
        return tto.rtg0 + tto.spent  # at t = 0: rtg_0 = −κ·J_REL(0)


class ValueRTG(RTGFeed):
    """``value``: −V(x_t, t), the model's value output; the ledger for a model without one (module doc)."""

    name, needs_value, fallback = "value", True, "running"

    def __call__(self, tto: TTOProvider, t: int) -> float | None:
        return -float(tto.planner.cost_to_go([tto.problem], tto.x[None], t)[0])


class OracleRTG(RTGFeed):
    """``oracle``: −J* of the remaining-horizon SCP optimum from the measured state (module doc)."""

    name = "oracle"

    def __init__(self, backend: str = "auto", plan: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        super().__init__(backend, plan)
        self.optimum = RemainingOptimum(plan, backend)

    def reset(self, scenario: Scenario, problem: Problem) -> None:
        self.optimum.reset(scenario, problem)

    def __call__(self, tto: TTOProvider, t: int) -> float | None:
        return -tto.scenario.cost(self.optimum(t, tto.x)[1])


RTG_MODES: dict[str, type[RTGFeed]] = {mode.name: mode for mode in (RunningRTG, ReanchorRTG, ValueRTG, OracleRTG)}


def rtg_feed(mode: str, planner: Planner) -> type[RTGFeed]:
    """The mode ``planner`` runs under ``rtg_mode=mode`` (``RTGFeed.for_model``); raises ``ValueError`` naming the
    modes for an unknown one."""
    if mode not in RTG_MODES:
        raise ValueError(f"rtg_mode must be one of {list(RTG_MODES)}, got {mode!r}")
    return RTG_MODES[mode].for_model(planner)
