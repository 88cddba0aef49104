"""Builders shared by several test modules (fixtures stay in conftest.py; this module is importable by name)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ttompc.policy.stats import NormStats
from ttompc.scenarios import get_scenario

if TYPE_CHECKING:
    from ttompc.policy import Planner


def toy_stats(seed: int = 0) -> NormStats:
    """Non-trivial statistics so that a missing (de)normalisation changes results."""
    rng = np.random.default_rng(seed)
    mean = {
        "states": rng.normal(size=6),
        "actions": rng.normal(size=3) * 0.1,
        "goals": rng.normal(size=6),
        "rtg": np.array([-3.0]),
        "ctg": np.array([0.5]),
    }
    std = {
        "states": rng.uniform(0.5, 2.0, 6),
        "actions": rng.uniform(0.1, 0.5, 3),
        "goals": rng.uniform(0.5, 2, 6),
        "rtg": np.array([2.0]),
        "ctg": np.array([1.0]),
    }
    return NormStats(mean, std)


def tiny_toy_planner(seed: int = 0) -> Planner:
    """A real (randomly initialised) planner on the "toy" scenario registered by conftest.py."""
    import torch

    from ttompc.policy import ModelConfig, Planner, TrajectoryGPT

    torch.manual_seed(seed)
    cfg = ModelConfig(n_embd=32, n_layer=2, n_head=2, max_steps=12, dropout=0.0)
    return Planner(TrajectoryGPT(cfg).eval(), get_scenario("toy"), toy_stats(seed))
