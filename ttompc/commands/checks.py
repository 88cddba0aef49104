"""Checks of command settings that the library would only reject deep inside a run (in a worker process, after
creating output folders): each raises a ``UserError`` naming the setting and the valid choices, before any work."""

from __future__ import annotations

import os
from pathlib import Path
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
    """``name`` must be one of ``ttompc.solvers.backends.BACKEND_NAMES`` (their solvers are all dependencies)."""
    from ttompc.solvers.backends import BACKEND_NAMES

    if name is not None and name not in BACKEND_NAMES:
        raise UserError(f"unknown solver backend {name!r}", f"choose one of: {', '.join(BACKEND_NAMES)}")


def seed(value: int, key: str = "seed") -> None:
    """Seeds feed ``numpy.random.SeedSequence``, which takes non-negative integers only."""
    if value < 0:
        raise UserError(f"{key} must be a non-negative integer, got {value}")


def solver(spec: str) -> None:
    """``spec`` names an importable function as ``module:function`` (``ttompc generate``'s ``solver``, which every
    worker process imports as the parent does here)."""
    import importlib

    module, sep, func = spec.partition(":")
    example = "e.g. solver=ttompc.solvers.scp:solve_problem (the default)"
    if not (module and sep and func):
        raise UserError(f"solver={spec!r} is not 'module:function'", example)
    try:
        found = getattr(importlib.import_module(module), func, None)
    except ImportError as err:
        raise UserError(f"solver={spec}: cannot import {module} ({err})", example) from None
    if not callable(found):
        raise UserError(f"solver={spec}: {module} has no function {func!r}", example)


def writable(path: str | Path) -> None:
    """The folder ``path`` can be created or written into: its nearest existing ancestor is a folder this process
    may write in. Checked without creating anything, so that an output a command may not write is refused (one line,
    worded as the CLI's error for such a path) before the work, not after it."""
    target = Path(path).absolute()
    existing = next(p for p in (target, *target.parents) if p.exists())
    reason = "not a directory" if not existing.is_dir() else None
    if reason is None and not os.access(existing, os.W_OK | os.X_OK):
        reason = "permission denied"
    if reason is not None:
        raise UserError(
            f"cannot use {existing} ({reason})", "choose a location you can write to, or fix its permissions"
        )
