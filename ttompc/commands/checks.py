"""Checks of command settings that the library would only reject deep inside a run (in a worker process, after
creating output folders): each raises a ``UserError`` naming the setting and the valid choices, before any work."""

from __future__ import annotations

from typing import TYPE_CHECKING

from ttompc.errors import UserError

if TYPE_CHECKING:
    from ttompc.scenarios import Scenario


def scenario(spec: str) -> Scenario:
    """The scenario ``spec`` names (a name, ``module:Class``, ``path/to/file.py:Class`` or an entry point), or a
    ``UserError`` saying what is missing (``ttompc.scenarios.ScenarioNotFoundError``)."""
    from ttompc.scenarios import get_scenario

    return get_scenario(spec)


def backend(name: str | None) -> None:
    """``name`` must be one of ``ttompc.solvers.backends.BACKEND_NAMES``, with its solver installed."""
    import importlib.util

    from ttompc.solvers.backends import BACKEND_NAMES

    if name is not None and name not in BACKEND_NAMES:
        raise UserError(f"unknown solver backend {name!r}", f"choose one of: {', '.join(BACKEND_NAMES)}")
    if name == "riccati" and importlib.util.find_spec("numba") is None:
        raise UserError("solver backend 'riccati' needs numba, which is not installed", "install ttompc[fast]")


def seed(value: int, key: str = "seed") -> None:
    """Seeds feed ``numpy.random.SeedSequence``, which takes non-negative integers only."""
    if value < 0:
        raise UserError(f"{key} must be a non-negative integer, got {value}")
