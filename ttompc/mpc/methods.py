"""The closed-loop methods, each registered once in ``METHODS``: its report name, whether it plans with a model and
with which (its model slot, ``ttompc.model_slots``: ``TTO``, ``FT-TTO`` for a fine-tuned one, None), whether it uses
the robust target, its tag in a model card's metrics (``ttompc.evaluation.card_metrics``), and the factory of its
providers (which take their name from it). Every other place that names a method derives it from here.

``ttompc evaluate mpc`` (``methods_for``), the closed-loop metrics of the training callback and of DAgger's
keep/reject decision, DAgger's learners and the demo all take their methods from here.

* REL-MPC and DIST-MPC (the paper's baselines; ``RELProvider``, ``DISTProvider``);
* PLAN-ONCE: the open-loop SCP optimum solved at t = 0, then MPC tracking it (no model, no re-planning;
  ``PlanProvider``);
* ORACLE-MPC, the ceiling: the full remaining-horizon SCP optimum from the measured state as warm start and target
  (``OracleProvider``);
* TTO-MPC (the paper's terminal target) and R-TTO-MPC (the target blended by ``robust_blend``,
  ``TerminalDesign.blend``), and the same for a fine-tuned model (FT-TTO-MPC, R-FT-TTO-MPC; ``TTOProvider``).

A method's providers are made from ``MethodInputs`` (one provider per episode of a lockstep batch; the TTO providers
of one method share a ``RolloutGroup``, one batched rollout per step), under ``MPCSettings``: the backend, the
terminal term of the plan-tracking providers (``terminal_term``) and the rtg mode of the model methods. A model
method's report name (``Method.label``) carries the rtg mode its model runs when that is not the paper's, e.g.
R-FT-TTO-MPC[rtg=value]; a model without a value output runs the ledger under ``value`` and is named without it.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ttompc.model_slots import FINE_TUNED, MODEL_SLOTS, PRETRAINED
from ttompc.mpc.providers import DISTProvider, OracleProvider, PlanProvider, Provider, RELProvider
from ttompc.mpc.rtg import rtg_feed
from ttompc.mpc.settings import MPCSettings
from ttompc.mpc.terminal import terminal_term
from ttompc.mpc.tto import RolloutGroup, TTOProvider

if TYPE_CHECKING:
    from ttompc.policy import Planner

ROBUST_BLEND = 0.95  # the target blend of the robust variants (R-TTO-MPC, R-FT-TTO-MPC; docs/evaluation.md)


@dataclass(frozen=True)
class MethodInputs:
    """What a method's providers are made from, for the B episodes of a lockstep batch: ``plans``, each episode's
    open-loop SCP optimum (``full_horizon_plan``: PLAN-ONCE's plan, ORACLE-MPC's first plan, the oracle rtg's; None:
    solved when the episode starts), the model of a model method, the target blend of the robust variants and the
    conditioning scale (rtg_0 = −``rtg_scale``·J_REL; None: the model's own, ``Planner.rtg_scale``)."""

    settings: MPCSettings
    plans: Sequence[tuple[np.ndarray, np.ndarray] | None]
    planner: Planner | None = None
    robust_blend: float = ROBUST_BLEND
    rtg_scale: float | None = None


@dataclass(frozen=True)
class Method:
    """A closed-loop method (module doc): ``name``, the model slot it plans with (None: no model), whether it uses
    the robust target, ``tag``, its key in a card's metrics (None: not on cards; a model method's is the same for
    either slot, the card's own), and ``build``, the factory of its providers."""

    name: str
    model: str | None
    robust: bool
    tag: str | None
    build: Callable[[Method, MethodInputs], list[Provider]]

    def label(self, settings: MPCSettings, planner: Planner | None = None) -> str:
        """The name reports give the method under ``settings`` with ``planner``: a model method's carries the rtg
        mode its model runs when it is not the paper's (``RTGFeed.label``)."""
        if self.model is None:
            return self.name
        if planner is None:
            raise ValueError(f"{self.name} plans with a model ({self.model}); none given")
        return self.name + rtg_feed(settings.rtg_mode, planner).label()

    def providers(self, inputs: MethodInputs) -> list[Provider]:
        """Fresh providers, one per episode of ``inputs.plans``."""
        if self.model is not None and inputs.planner is None:
            raise ValueError(f"{self.name} plans with a model ({self.model}); none given")
        if self.robust and not inputs.robust_blend > 0:
            raise ValueError(f"{self.name} needs a robust_blend > 0, got {inputs.robust_blend}")
        return self.build(self, inputs)


def _rel(method: Method, x: MethodInputs) -> list[Provider]:
    return [RELProvider(x.settings.backend, name=method.name) for _ in x.plans]


def _dist(method: Method, x: MethodInputs) -> list[Provider]:
    return [DISTProvider(x.settings.backend, name=method.name) for _ in x.plans]


def _plan_once(method: Method, x: MethodInputs) -> list[Provider]:
    s = x.settings
    return [PlanProvider(plan, name=method.name, backend=s.backend, terminal=terminal_term(s)) for plan in x.plans]


def _oracle(method: Method, x: MethodInputs) -> list[Provider]:
    s = x.settings
    return [OracleProvider(plan, name=method.name, backend=s.backend, terminal=terminal_term(s)) for plan in x.plans]


def _tto(method: Method, x: MethodInputs) -> list[Provider]:
    planner, s = x.planner, x.settings
    assert planner is not None  # Method.providers checked it
    group, name = RolloutGroup(planner, decode_every=s.decode_every, decoder=s.decoder), method.label(s, planner)
    blend = x.robust_blend if method.robust else 0.0
    return [
        TTOProvider(
            planner,
            name,
            rtg_scale=x.rtg_scale,
            terminal=terminal_term(s, blend, planner),  # one per episode: the robust target remembers its last
            rtg_mode=s.rtg_mode,
            group=group,
            backend=s.backend,
            plan=plan,
        )
        for plan in x.plans
    ]


METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        Method("REL-MPC", None, False, "rel", _rel),
        Method("DIST-MPC", None, False, None, _dist),
        Method("PLAN-ONCE", None, False, "planonce", _plan_once),
        Method("ORACLE-MPC", None, False, "oracle", _oracle),
        Method("TTO-MPC", PRETRAINED, False, "model", _tto),
        Method("R-TTO-MPC", PRETRAINED, True, "robust", _tto),
        Method("FT-TTO-MPC", FINE_TUNED, False, "model", _tto),
        Method("R-FT-TTO-MPC", FINE_TUNED, True, "robust", _tto),
    )
}
BASELINE, CEILING, REFERENCE = "REL-MPC", "ORACLE-MPC", "DIST-MPC"  # the reports' roles of three methods


def methods_for(models: Collection[str], robust_blend: float = ROBUST_BLEND) -> list[Method]:
    """The methods ``ttompc evaluate mpc`` runs with the model slots ``models`` filled, in ``METHODS`` order: every
    method without a model, and each filled slot's, its robust variant only when ``robust_blend`` > 0."""
    unknown = set(models) - set(MODEL_SLOTS)
    if unknown:
        raise ValueError(f"model slots must be among {list(MODEL_SLOTS)}, got {sorted(unknown)}")
    return [
        m for m in METHODS.values() if (m.model is None or m.model in models) and (not m.robust or robust_blend > 0)
    ]


def base_method(label: str) -> str:
    """The method of a report's name (``Method.label``) without its rtg-mode label: ``FT-TTO-MPC[rtg=value]`` ->
    ``FT-TTO-MPC``."""
    return label.split("[", 1)[0]


def model_method(slot: str, robust: bool = False) -> Method:
    """The method of the model slot ``slot`` ("TTO", "FT-TTO"), robust or not."""
    found = [m for m in METHODS.values() if m.model == slot and m.robust == robust]
    if not found:
        raise ValueError(f"no method plans with the model slot {slot!r} (slots: {list(MODEL_SLOTS)})")
    return found[0]
