"""The trajectory transformer: config and model (plain PyTorch; no Lightning import)."""

from ttompc.model.config import ModelConfig
from ttompc.model.gpt import KVCache, TrajectoryGPT

__all__ = ["KVCache", "ModelConfig", "TrajectoryGPT"]
