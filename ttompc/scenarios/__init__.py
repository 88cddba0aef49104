"""Scenario registry: ``get_scenario(spec)`` for the built-in scenarios and for your own.

A *spec* names a scenario in any process (docs/scenarios.md):

* a registered name: the built-ins ("freeflyer", "quadrotor", "rpod") and classes decorated with ``@register``;
* the name of an entry point in the group ``ttompc.scenarios``, how an installed package offers its scenarios
  (``[project.entry-points."ttompc.scenarios"] di2d = "mypkg.di2d:DoubleIntegrator2D"`` in its pyproject.toml);
* ``module:Class`` (an importable module) or ``path/to/file.py:Class`` (a file, for quick work).

Loading a spec registers its class under ``Scenario.name`` for this process, so code that passes names around keeps
working. ``scenario_spec`` is the spec that finds a scenario again in another process: datasets, checkpoints and
planner bundles record it next to the name (``find_scenario`` reads it back), and pool workers load it before their
first task (``ttompc.parallel.pool_map``). Scenarios plug into the one SCP engine, dataset generator, rollout and MPC
loop without touching them.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.metadata
import importlib.util
import inspect
import sys
from pathlib import Path
from typing import Any

from ttompc.errors import UserError
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

ENTRY_POINT_GROUP = "ttompc.scenarios"
_REGISTRY: dict[str, type[Scenario]] = {}
# Built-in scenarios are imported on first use so that importing the registry stays cheap.
_BUILTIN = {
    "freeflyer": "ttompc.scenarios.freeflyer",
    "quadrotor": "ttompc.scenarios.quadrotor",
    "rpod": "ttompc.scenarios.rpod",
}
_INSTANCES: dict[str, Scenario] = {}
_SPECS: dict[str, str] = {}  # name -> the spec it was loaded from (entry point name, module:Class, /abs/file.py:Class)
_LOADED: dict[str, str] = {}  # spec as given -> name, so a spec is resolved once per process
_FORMS = "or pass module:Class, path/to/file.py:Class or an entry point of the group 'ttompc.scenarios'"


class ScenarioNotFoundError(UserError, LookupError):
    """A spec that names no usable scenario: unknown name, missing module, file or class, or not a ``Scenario``."""


def register(cls: type[Scenario]) -> type[Scenario]:
    """Class decorator adding a scenario to the registry under ``cls.name``."""
    if cls.name in _REGISTRY and _REGISTRY[cls.name] is not cls:
        raise ValueError(f"scenario {cls.name!r} is already registered by {_REGISTRY[cls.name].__qualname__}")
    _REGISTRY[cls.name] = cls
    return cls


def list_scenarios() -> list[str]:
    """Registered, built-in and installed (entry point) scenario names."""
    return sorted(set(_REGISTRY) | set(_BUILTIN) | set(_entry_points()))


def get_scenario(spec: str) -> Scenario:
    """The (stateless, shared) instance of the scenario ``spec`` names (see the module docstring); raises
    ``ScenarioNotFoundError`` naming what is missing (also for a ``spec`` that is not a string)."""
    if not isinstance(spec, str):
        raise ScenarioNotFoundError(
            f"unknown scenario {spec!r}", f"choose one of: {', '.join(list_scenarios())}, {_FORMS}"
        )
    name = spec if spec in _REGISTRY else _LOADED.get(spec) or _load(spec)
    if name not in _INSTANCES:
        _INSTANCES[name] = _REGISTRY[name]()
    return _INSTANCES[name]


def scenario_spec(scenario: Scenario | str) -> str:
    """The spec that loads ``scenario`` (an instance or a registered name) in a fresh process: the name for built-in
    and entry-point scenarios, the loaded spec (files as absolute paths), else ``module:Class`` of its class."""
    name = scenario if isinstance(scenario, str) else scenario.name
    if name in _BUILTIN:
        return name
    if name in _SPECS:
        return _SPECS[name]
    cls = type(get_scenario(name))
    return f"{cls.__module__}:{cls.__qualname__}"


def find_scenario(name: str, spec: str | None = None) -> Scenario:
    """The scenario a dataset, checkpoint or bundle recorded as (``name``, ``spec``): by name when this process
    knows it (built in, or loaded before), else from the recorded spec."""
    known = name in _REGISTRY or name in _BUILTIN
    return get_scenario(name if known or not spec else spec)


# ------------------------------------------------------------------------------------------------------ loading
def _entry_points() -> dict[str, importlib.metadata.EntryPoint]:
    return {ep.name: ep for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}


def _load(spec: str) -> str:
    """Import what ``spec`` names and register its class; returns the scenario's name."""
    if spec in _BUILTIN:
        importlib.import_module(_BUILTIN[spec])
        return spec
    entry = _entry_points().get(spec)
    if entry is not None:
        where, attr = entry.module, entry.attr
        cls = _attribute(_import_module(where, f"entry point {spec!r}"), attr, f"entry point {spec!r} ({entry.value})")
        return _adopt(cls, spec, spec)
    where, sep, attr = spec.rpartition(":")
    if not sep or not where or not attr:
        raise ScenarioNotFoundError(
            f"unknown scenario {spec!r}", f"choose one of: {', '.join(list_scenarios())}, {_FORMS}"
        )
    if where.endswith(".py") or "/" in where or "\\" in where:
        path = Path(where).expanduser().resolve()
        module = _import_file(path, spec)
        return _adopt(_attribute(module, attr, spec), spec, f"{path}:{attr}")
    return _adopt(_attribute(_import_module(where, spec), attr, spec), spec, spec)


def _import_module(module: str, what: str) -> Any:
    """Import ``module``; a missing module (not a missing import inside it) is a one-line error."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as err:
        if err.name is None or not (module == err.name or module.startswith(f"{err.name}.")):
            raise  # the module exists but one of its own imports is missing: the traceback shows where
        raise ScenarioNotFoundError(
            f"{what}: no module named {module!r}",
            "install the package that provides it, or check the module path (PYTHONPATH)",
        ) from None


def _import_file(path: Path, spec: str) -> Any:
    """Execute a scenario file once per process as a module named after its absolute path (the same name in every
    process, so pickled objects of its classes resolve in pool workers once they loaded the spec)."""
    if not path.is_file():
        raise ScenarioNotFoundError(
            f"{spec}: scenario file {path} not found", "check the path (a relative path starts from the current folder)"
        )
    digest = hashlib.sha256(str(path).encode()).hexdigest()[:12]
    module_name = f"ttompc_user_scenario_{digest}"
    if module_name in sys.modules:
        return sys.modules[module_name]
    loader_spec = importlib.util.spec_from_file_location(module_name, path)
    if loader_spec is None or loader_spec.loader is None:
        raise ScenarioNotFoundError(f"{spec}: {path} is not a Python file", "name a .py file")
    module = importlib.util.module_from_spec(loader_spec)
    sys.modules[module_name] = module  # before executing it: dataclasses and pickle look the module up by name
    try:
        loader_spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[module_name]
        raise
    return module


def _attribute(module: Any, attr: str, what: str) -> Any:
    try:
        return getattr(module, attr)
    except AttributeError:
        classes = sorted(
            n for n, v in vars(module).items() if inspect.isclass(v) and issubclass(v, Scenario) and v is not Scenario
        )
        hint = f"it defines: {', '.join(classes)}" if classes else "it defines no Scenario subclass"
        raise ScenarioNotFoundError(f"{what}: {module.__name__} has no attribute {attr!r}", hint) from None


def _adopt(cls: Any, spec: str, recorded: str) -> str:
    """Register the class ``spec`` resolved to (``recorded`` is what ``scenario_spec`` will return for it)."""
    if not (inspect.isclass(cls) and issubclass(cls, Scenario)):
        raise ScenarioNotFoundError(
            f"{spec} is {type(cls).__name__} {cls!r}, not a Scenario subclass",
            "name a class that subclasses ttompc.scenarios.Scenario (docs/scenarios.md)",
        )
    if inspect.isabstract(cls):
        missing = ", ".join(sorted(cls.__abstractmethods__))
        raise ScenarioNotFoundError(f"{spec}: {cls.__qualname__} does not implement {missing}", "see docs/scenarios.md")
    name = getattr(cls, "name", None)
    if not isinstance(name, str) or not name:
        raise ScenarioNotFoundError(
            f"{spec}: {cls.__qualname__} has no 'name' (a class attribute, e.g. name = \"di2d\")"
        )
    if name in _BUILTIN:
        importlib.import_module(_BUILTIN[name])  # a built-in's name is taken even before its first use
    if name in _REGISTRY and _REGISTRY[name] is not cls:
        other = _REGISTRY[name]
        raise ScenarioNotFoundError(
            f"{spec}: scenario name {name!r} is already taken by {other.__module__}.{other.__qualname__}",
            "give your scenario another name",
        )
    _REGISTRY[name] = cls
    _SPECS[name] = recorded
    _LOADED[spec] = name
    return name


__all__ = [
    "ENTRY_POINT_GROUP",
    "BatchedModel",
    "BlockKind",
    "ConstraintBlock",
    "ConvexModel",
    "InfeasibleProblemError",
    "MPCWeights",
    "Problem",
    "SCPSettings",
    "Scenario",
    "ScenarioNotFoundError",
    "Window",
    "find_scenario",
    "get_scenario",
    "list_scenarios",
    "register",
    "scenario_spec",
    "stage_cost",
]
