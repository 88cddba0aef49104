"""ttompc: transformer-guided trajectory optimization and model predictive control.

Heavy pieces (torch, Lightning) are imported lazily so that solvers and scenarios stay fast to import.
"""

from __future__ import annotations

from typing import Any

__version__ = "0.1.0"

_LAZY = {
    "get_scenario": ("ttompc.scenarios", "get_scenario"),
    "list_scenarios": ("ttompc.scenarios", "list_scenarios"),
    "load_pretrained": ("ttompc.zoo", "load_pretrained"),
    "solve_problem": ("ttompc.solvers", "solve_problem"),
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'ttompc' has no attribute {name!r}")


__all__ = ["__version__", *_LAZY]
