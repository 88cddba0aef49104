"""Checks of command settings that the library would only reject deep inside a run (in a worker process, after
creating output folders): each raises a ``UserError`` naming the setting and the valid choices, before any work."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from ttompc.errors import UserError
from ttompc.outputs import writable

__all__ = ["backend", "figure_file", "scenario", "solver", "writable"]  # writable: ttompc.outputs'

if TYPE_CHECKING:
    from ttompc.scenarios import Scenario


def scenario(spec: str) -> Scenario:
    """The scenario ``spec`` names (a name, ``module:Class``, ``path/to/file.py:Class`` or an entry point), or a
    ``UserError`` saying what is missing (``ttompc.scenarios.ScenarioNotFoundError``)."""
    from ttompc.scenarios import get_scenario

    return get_scenario(spec)


def backend(name: str | None) -> None:
    """``name`` must be one of ``ttompc.solvers.backends.BACKEND_NAMES`` (their solvers are all dependencies):
    ``check_backend``, which the solvers run too."""
    from ttompc.solvers.backends.chain import check_backend

    if name is not None:
        check_backend(name)


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


def figure_file(path: str | Path, key: str) -> None:
    """``path`` (the setting ``key``) names an image file matplotlib can write: not a folder, with the suffix of a
    format it knows (it would otherwise append ``.png`` to the name, or fail after the work), in a writable place."""
    from matplotlib.backend_bases import FigureCanvasBase

    target = Path(path)
    if target.is_dir():
        raise UserError(f"{key}={path} is a folder", f"name an image file, e.g. {target / 'plot.png'}")
    formats = FigureCanvasBase.get_supported_filetypes()
    suffix = target.suffix.lstrip(".").lower()
    if suffix not in formats:
        what = f".{suffix} is not an image format matplotlib writes" if suffix else "the file name has no suffix"
        raise UserError(f"{key}={path}: {what}", f"use one of {', '.join('.' + f for f in sorted(formats))}")
    writable(target.parent)
