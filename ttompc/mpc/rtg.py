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
training rows' rtg lie in (``TTOProvider.conditioning``). The episodes of a ``RolloutGroup`` run in lockstep, and a
mode may do the work its members share at a step once for all of them before each member's call (``prepare``:
``value`` prices every member's state in one batched call of the value output). Adding a mode is a class here, its
entry in ``RTG_MODES`` and the presets that name it.

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
from collections.abc import Sequence
from typing import TYPE_CHECKING, ClassVar, Protocol

import numpy as np

from ttompc.mpc.providers import RemainingOptimum, RemainingREL
from ttompc.mpc.settings import register_names
from ttompc.scenarios.base import Problem, Scenario

if TYPE_CHECKING:
    from ttompc.policy import Planner


class Fed(Protocol):
    """What a mode reads of the provider it feeds (a ``ttompc.mpc.tto.TTOProvider``): its episode, measured state,
    model, own feed and ledger."""

    @property
    def scenario(self) -> Scenario: ...
    @property
    def problem(self) -> Problem: ...
    @property
    def x(self) -> np.ndarray: ...
    @property
    def planner(self) -> Planner: ...
    @property
    def rtg(self) -> RTGFeed: ...
    @property
    def rtg_mode(self) -> str: ...
    @property
    def rtg0(self) -> float: ...
    @property
    def rtg_scale(self) -> float: ...
    @property
    def spent(self) -> float: ...


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

    @classmethod  # noqa: B027 (most modes share no work)
    def prepare(cls, members: Sequence[Fed], t: int) -> None:
        """Do at once the work that the feeds of ``members`` (episodes in lockstep running this mode, sharing one
        planner: a ``RolloutGroup``'s) share at step t, before each member's call at step t from its measured state
        ``tto.x``; a call without it gives the same value, up to float rounding."""

    @abstractmethod
    def __call__(self, tto: Fed, t: int) -> float | None:
        """The rtg to feed ``tto``'s model at step t from its measured state ``tto.x`` (unclipped; None: the
        context's running value)."""


class RunningRTG(RTGFeed):
    """``running``: the paper's ledger (module doc)."""

    name, paper = "running", True

    def __call__(self, tto: Fed, t: int) -> float | None:
        return None


class ReanchorRTG(RTGFeed):
    """``reanchor``: −κ·J_REL of the remaining horizon from the measured state (module doc)."""

    name = "reanchor"

    def __init__(self, backend: str = "auto", plan: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        super().__init__(backend, plan)
        self.rel = RemainingREL(backend)

    def reset(self, scenario: Scenario, problem: Problem) -> None:
        self.rel.reset()

    def __call__(self, tto: Fed, t: int) -> float | None:
        if t > 0:
            rel = self.rel(tto.scenario, tto.problem, t, tto.x)
            if rel.success:
                return -tto.rtg_scale * rel.cost
        return tto.rtg0 + tto.spent  # at t = 0: rtg_0 = −κ·J_REL(0)


class ValueRTG(RTGFeed):
    """``value``: −V(x_t, t), the model's value output; the ledger for a model without one (module doc). The
    members of a lockstep step are priced in one batched call (``prepare``); a call at a state ``prepare`` did not
    price is priced alone (batch 1)."""

    name, needs_value, fallback = "value", True, "running"

    def __init__(self, backend: str = "auto", plan: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        super().__init__(backend, plan)
        self.priced: tuple[int, np.ndarray, float] | None = None  # (t, x_t, V(x_t, t)) from ``prepare``, unread

    @classmethod
    def prepare(cls, members: Sequence[Fed], t: int) -> None:
        """V(x_t, t) of every member's measured state (B >= 1 members) in one ``Planner.cost_to_go`` call of batch
        B, kept for the member's next call (its row of the batch; a feed reads a priced value once)."""
        feeds = [m.rtg for m in members if isinstance(m.rtg, ValueRTG)]
        if len(feeds) != len(members):
            raise TypeError(f"rtg_mode=value prices the members that run it, not {[m.rtg_mode for m in members]}")
        V = members[0].planner.cost_to_go([m.problem for m in members], np.stack([m.x for m in members]), t)
        for m, feed, v in zip(members, feeds, V, strict=True):
            feed.priced = (t, np.array(m.x), float(v))

    def __call__(self, tto: Fed, t: int) -> float | None:
        priced, self.priced = self.priced, None
        if priced is not None and priced[0] == t and np.array_equal(priced[1], tto.x):
            return -priced[2]
        return -float(tto.planner.cost_to_go([tto.problem], tto.x[None], t)[0])


class OracleRTG(RTGFeed):
    """``oracle``: −J* of the remaining-horizon SCP optimum from the measured state (module doc)."""

    name = "oracle"

    def __init__(self, backend: str = "auto", plan: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        super().__init__(backend, plan)
        self.optimum = RemainingOptimum(plan, backend)

    def reset(self, scenario: Scenario, problem: Problem) -> None:
        self.optimum.reset(scenario, problem)

    def __call__(self, tto: Fed, t: int) -> float | None:
        return -tto.scenario.cost(self.optimum(t, tto.x)[1])


RTG_MODES: dict[str, type[RTGFeed]] = {mode.name: mode for mode in (RunningRTG, ReanchorRTG, ValueRTG, OracleRTG)}
register_names("rtg_mode", RTG_MODES)


def rtg_feed(mode: str, planner: Planner) -> type[RTGFeed]:
    """The mode ``planner`` runs under ``rtg_mode=mode`` (``RTGFeed.for_model``); raises ``ValueError`` naming the
    modes for an unknown one."""
    if mode not in RTG_MODES:
        raise ValueError(f"rtg_mode must be one of {list(RTG_MODES)}, got {mode!r}")
    return RTG_MODES[mode].for_model(planner)
