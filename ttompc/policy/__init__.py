"""The policy: the trajectory transformer (``config``, ``gpt``), its normalisation statistics (``stats``), the
model-based rollout (``rollout``) and ``Planner`` (model + scenario + statistics, with the one loader
``Planner.from_pretrained``).

The one-shot ``rollout`` function is ``ttompc.policy.rollout.rollout`` (the name ``rollout`` here is the module).
Names load on first use, so ``ttompc.policy.stats`` (numpy only) can be imported by the data package without torch.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ttompc.policy.config import ModelConfig
    from ttompc.policy.gpt import Decoder, KVCache, TrajectoryGPT
    from ttompc.policy.planner import Planner
    from ttompc.policy.rollout import RolloutContext, RolloutResult
    from ttompc.policy.stats import NormStats

_LAZY = {
    "ModelConfig": "ttompc.policy.config",
    "Decoder": "ttompc.policy.gpt",
    "KVCache": "ttompc.policy.gpt",
    "TrajectoryGPT": "ttompc.policy.gpt",
    "NormStats": "ttompc.policy.stats",
    "RolloutContext": "ttompc.policy.rollout",
    "RolloutResult": "ttompc.policy.rollout",
    "Planner": "ttompc.policy.planner",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "Decoder",
    "KVCache",
    "ModelConfig",
    "NormStats",
    "Planner",
    "RolloutContext",
    "RolloutResult",
    "TrajectoryGPT",
]
