"""Typed DAgger fine-tuning recipe (``recipes/<scenario>/finetune.yaml``): the training sections of
``TrainConfig`` (data, optim, trainer, logger; ``model`` comes from the pretrained model) plus ``dagger``.

``trainer.max_steps`` is not used: each DAgger iteration trains ``dagger.steps_per_iteration`` optimiser steps, and
global steps continue across iterations (iteration i ends at (i+1)·steps_per_iteration). The open-loop/closed-loop
mix is ``data.open_loop_fraction`` with ``data.closed_loop_share`` "fixed" (that fraction at every iteration, the
default) or "grow" (the reference's schedule: 9:1 at the first iteration, then a growing closed-loop share).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ttompc.config import ConfigError, load_command_config
from ttompc.data.config import DataConfig
from ttompc.training.config import LoggerConfig, OptimConfig, TrainerConfig


@dataclass
class ExplorationConfig:
    """Exploration policy of a rollout (paper Alg. 1, fact sheet §5.3): the learner is TTO-MPC with H drawn
    uniformly from ``horizons``; the expert acts inside ``windows`` = U{min..max} windows of U{min..max} steps,
    one of them covering the end of the episode when ``end_window``."""

    horizons: list[int] = field(default_factory=lambda: list(range(10, 101, 10)))
    windows: list[int] = field(default_factory=lambda: [1, 3])
    window_length: list[int] = field(default_factory=lambda: [15, 25])
    end_window: bool = True

    def __post_init__(self) -> None:
        for name in ("windows", "window_length"):
            lo_hi = getattr(self, name)
            if len(lo_hi) != 2 or lo_hi[0] > lo_hi[1] or lo_hi[0] < 0:
                raise ValueError(f"dagger.exploration.{name} must be [min, max] with 0 <= min <= max, got {lo_hi}")
        if not self.horizons or min(self.horizons) < 1:
            raise ValueError(f"dagger.exploration.horizons must be positive, got {self.horizons}")


@dataclass
class CollectConfig:
    rollouts: int = 2000  # closed-loop rollouts per iteration (all ranks together)
    workers: int = 0  # processes per rank (spawn pool); 0 = all cores
    shard_size: int = 50  # rollouts per shard (the unit of resumption and of the rank split)
    val_fraction: float = 0.1  # share of rollouts written to the DAgger val split (by rollout index hash)
    mode: str = "soft"
    backend: str = "auto"
    wait_s: float = 3600.0  # multi-rank: how long to wait for other ranks' shards and rank 0's checkpoints


@dataclass
class EvalConfig:
    """Closed-loop TTO-MPC metrics logged before the first and after every iteration."""

    problems: int = 4
    horizon: int = 10
    max_steps: int | None = None
    seed: int = 0


@dataclass
class DaggerConfig:
    iterations: int = 10
    seed: int = 0  # root seed: rollout (i, r) uses SeedSequence(seed, spawn_key=(stream, i, r))
    steps_per_iteration: int = 3000
    exploration: ExplorationConfig = field(default_factory=ExplorationConfig)
    collect: CollectConfig = field(default_factory=CollectConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)

    def __post_init__(self) -> None:
        if self.iterations < 1 or self.steps_per_iteration < 1 or self.collect.rollouts < 1:
            raise ValueError("dagger.iterations, dagger.steps_per_iteration and dagger.collect.rollouts must be >= 1")
        if not 0.0 <= self.collect.val_fraction < 1.0:
            raise ValueError(f"dagger.collect.val_fraction must be in [0, 1), got {self.collect.val_fraction}")


@dataclass
class FinetuneConfig:
    dagger: DaggerConfig = field(default_factory=DaggerConfig)
    data: DataConfig = field(default_factory=DataConfig)
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(lr=3e-5, warmup_steps=0))
    trainer: TrainerConfig = field(default_factory=lambda: TrainerConfig(out_dir="runs/freeflyer-dagger"))
    logger: LoggerConfig = field(default_factory=LoggerConfig)


def load_finetune_config(path: str | Path | None = None, overrides: Sequence[str] = ()) -> FinetuneConfig:
    """Load and validate a fine-tuning recipe (schema <- YAML <- ``key=value`` overrides)."""
    try:
        return load_command_config(FinetuneConfig, path, overrides)
    except ConfigError:
        raise
    except ValueError as err:
        raise ConfigError(f"invalid config ({path or 'defaults'}): {err}") from None
