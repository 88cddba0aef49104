"""Trajectory datasets: generation, parquet shards (and their one resumable writer), splits, cards and the streaming
DataModule.

Only light modules are imported eagerly; ``datasets`` and Lightning load on first use of the names below, so
``import ttompc.data`` stays fast and never imports Lightning.
"""

from __future__ import annotations

import importlib
from typing import Any

from ttompc.data.config import DataConfig, GenerateConfig, SplitConfig
from ttompc.policy.stats import NormStats

_LAZY = {
    "TrajectoryDataModule": "ttompc.data.datamodule",
    "ShardError": "ttompc.data.shards",
    "ShardWriter": "ttompc.data.shards",
    "ShardedFolder": "ttompc.data.resumable",
    "write_shard": "ttompc.data.shards",
    "read_shard": "ttompc.data.shards",
    "make_row": "ttompc.data.schema",
    "trajectory_features": "ttompc.data.schema",
    "generate": "ttompc.data.generate",
    "load_manifest": "ttompc.data.generate",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["DataConfig", "GenerateConfig", "NormStats", "SplitConfig", *_LAZY]
