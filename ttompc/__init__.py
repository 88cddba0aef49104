"""ttompc: transformer-guided trajectory optimization and model predictive control.

Heavy pieces (torch, Lightning) are imported lazily so that solvers and scenarios stay fast to import.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

if TYPE_CHECKING:
    from ttompc.mpc.controller import Controller
    from ttompc.policy import Planner
    from ttompc.scenarios import get_scenario, list_scenarios
    from ttompc.solvers import solve_problem

    load_pretrained = Planner.from_pretrained

# name -> (module, dotted attribute); ``load_pretrained`` is ``Planner.from_pretrained`` itself, not a copy
_LAZY = {
    "Controller": ("ttompc.mpc.controller", "Controller"),
    "get_scenario": ("ttompc.scenarios", "get_scenario"),
    "list_scenarios": ("ttompc.scenarios", "list_scenarios"),
    "load_pretrained": ("ttompc.policy.planner", "Planner.from_pretrained"),
    "Planner": ("ttompc.policy.planner", "Planner"),
    "solve_problem": ("ttompc.solvers", "solve_problem"),
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        module, path = _LAZY[name]
        obj: Any = importlib.import_module(module)
        for attr in path.split("."):
            obj = getattr(obj, attr)
        return obj
    raise AttributeError(f"module 'ttompc' has no attribute {name!r}")


__all__ = ["Controller", "Planner", "__version__", "get_scenario", "list_scenarios", "load_pretrained", "solve_problem"]
