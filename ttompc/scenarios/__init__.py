"""Scenario registry: ``get_scenario("freeflyer")``. New scenarios register with ``@register`` and plug into the
one SCP engine, dataset generator, rollout and MPC loop without touching them."""

from __future__ import annotations

import importlib

from ttompc.scenarios.base import (
    BatchedModel,
    BlockKind,
    ConstraintBlock,
    ConvexModel,
    InfeasibleProblemError,
    MPCWeights,
    Problem,
    Scenario,
    SCPSettings,
    Window,
    stage_cost,
)

_REGISTRY: dict[str, type[Scenario]] = {}
# Built-in scenarios are imported on first use so that importing the registry stays cheap.
_BUILTIN = {
    "freeflyer": "ttompc.scenarios.freeflyer",
    "quadrotor": "ttompc.scenarios.quadrotor",
    "rpod": "ttompc.scenarios.rpod",
}
_INSTANCES: dict[str, Scenario] = {}


def register(cls: type[Scenario]) -> type[Scenario]:
    """Class decorator adding a scenario to the registry under ``cls.name``."""
    if cls.name in _REGISTRY and _REGISTRY[cls.name] is not cls:
        raise ValueError(f"scenario {cls.name!r} is already registered by {_REGISTRY[cls.name].__qualname__}")
    _REGISTRY[cls.name] = cls
    return cls


def list_scenarios() -> list[str]:
    return sorted(set(_REGISTRY) | set(_BUILTIN))


def get_scenario(name: str) -> Scenario:
    """The (stateless, shared) scenario instance registered under ``name``."""
    if name not in _REGISTRY and name in _BUILTIN:
        importlib.import_module(_BUILTIN[name])
    if name not in _REGISTRY:
        raise KeyError(f"unknown scenario {name!r}; available: {', '.join(list_scenarios())}")
    if name not in _INSTANCES:
        _INSTANCES[name] = _REGISTRY[name]()
    return _INSTANCES[name]


__all__ = [
    "BatchedModel",
    "BlockKind",
    "ConstraintBlock",
    "ConvexModel",
    "InfeasibleProblemError",
    "MPCWeights",
    "Problem",
    "SCPSettings",
    "Scenario",
    "Window",
    "get_scenario",
    "list_scenarios",
    "register",
    "stage_cost",
]
