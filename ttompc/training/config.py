"""Typed training recipe: ``TrainConfig`` = model + data + optimiser + trainer + logger + callbacks sections.

Recipes (``recipes/<scenario>/pretrain.yaml`` and ``tiny.yaml``, ``recipes/generic/``, ``recipes/zoo/``) are
loaded with ``load_train_config`` (schema defaults <- YAML <- ``key=value`` overrides); unknown keys and wrong types
raise ``ConfigError`` naming the key. This module does not import Lightning.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from ttompc.config import ConfigError, given_keys, load_command_config
from ttompc.data.config import DataConfig
from ttompc.evaluation.measurement import Measurement
from ttompc.policy.config import ModelConfig
from ttompc.ranges import Checked, setting

# what ``lightning.Trainer(precision=...)`` accepts (checked when the recipe loads, not when training starts)
LightningPrecision = Literal[
    "64-true",
    "32-true",
    "16-true",
    "bf16-true",
    "16-mixed",
    "bf16-mixed",
    "transformer-engine",
    "transformer-engine-float16",
    "64",
    "32",
    "16",
    "bf16",
]
# and "auto": bf16-mixed where the training device computes bf16 natively, else 32-true (ttompc.training.precision)
Precision = Literal["auto", LightningPrecision]


@dataclass
class OptimConfig(Checked):
    """AdamW with linear warm-up, then a constant or cosine learning rate (per optimiser step)."""

    lr: float = setting(3e-4, gt=0)
    weight_decay: float = setting(0.01, ge=0)  # applied to matrices and embeddings only, not to biases and norms
    betas: list[float] = setting(factory=lambda: [0.9, 0.999], ge=0, lt=1)
    warmup_steps: int = setting(100, ge=0)
    schedule: Literal["constant", "cosine"] = "constant"
    min_lr_ratio: float = setting(0.1, ge=0, le=1)  # cosine floor as a fraction of lr
    grad_clip: float = setting(1.0, ge=0, meaning="0: off")  # global-norm clipping
    accumulate: int = setting(1, ge=1)  # micro-batches per optimiser step
    # training loss: None = MSE (the paper); a number = Huber beyond that many normalised units (docs/training.md)
    huber_delta: float | None = setting(None, gt=0)
    # "all", or "value": train the value output alone on a frozen policy (adds a value to a published model without
    # changing its plans; the transformer is not run)
    trainable: Literal["all", "value"] = "all"
    # the value loss weighs steps with at most ``value_tail_steps`` steps to go (N = model.max_steps) by
    # ``value_tail_weight``: where a short MPC window's terminal cost reads the value (0: every step alike)
    value_tail_steps: int = setting(0, ge=0)
    value_tail_weight: float = setting(1.0, gt=0)
    # a Sobolev term: the weight of the value's gradient error against the rows' costates (0: the value alone)
    value_grad_weight: float = setting(0.0, ge=0)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.trainable not in ("all", "value"):
            raise ValueError(f"optim.trainable must be 'all' or 'value', got {self.trainable!r}")
        if len(self.betas) != 2:
            raise ValueError(f"invalid optim.betas={self.betas}: needs two values")


@dataclass
class TrainerConfig(Checked):
    max_steps: int = setting(100_000, ge=1, also=(-1,), meaning="-1: until max_epochs")  # optimiser steps
    max_epochs: int | None = setting(None, ge=1)
    # <= 1: fraction of an epoch; > 1: every that many training batches
    val_check_interval: float = setting(1.0, gt=0)
    limit_val_batches: float = setting(1.0, ge=0, meaning="<= 1: a fraction; > 1: a number of batches; 0: none")
    checkpoint_every_n_steps: int = setting(1000, ge=1)  # refreshes last.ckpt and writes step<N>.ckpt
    keep_checkpoints: int = setting(3, ge=0, also=(-1,), meaning="-1: all")  # most recent step<N>.ckpt files kept
    log_every_n_steps: int = setting(50, ge=1)
    devices: int = setting(1, ge=1, also=(-1,), per_core=4, meaning="-1: all")  # processes on this machine
    num_nodes: int = setting(1, ge=1)
    accelerator: str = setting("auto", device="lightning")
    strategy: str = "auto"  # e.g. ddp, ddp_spawn, fsdp
    precision: Precision = "auto"  # resolved when the Trainer is built; the checkpoint records what ran
    num_sanity_val_steps: int = setting(0, ge=0, also=(-1,), meaning="-1: all")
    seed: int = setting(0, ge=0, le=2**32 - 1)
    out_dir: str = "runs/freeflyer-pretrain"
    resume: bool = True  # continue from <out_dir>/checkpoints/last.ckpt when it exists
    export_planner: bool = True  # write <out_dir>/planner/ after training

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.max_steps == -1 and self.max_epochs is None:
            raise ValueError("invalid trainer.max_steps=-1: it trains until trainer.max_epochs, which is null")
        for key in ("val_check_interval", "limit_val_batches"):  # above 1 Lightning counts batches: no fraction
            value = getattr(self, key)
            if value > 1 and not float(value).is_integer():
                raise ValueError(
                    f"invalid trainer.{key}={value}: <= 1 is a fraction, above it a whole number of batches"
                )


@dataclass
class LoggerConfig:
    kind: Literal["wandb", "csv", "tensorboard", "none"] = "wandb"
    project: str = "ttompc"
    name: str | None = None
    mode: Literal["online", "offline", "disabled"] | None = None  # None: see ``wandb_mode``
    plot_trajectories: bool = True  # a predicted-vs-target trajectory figure at every validation end

    def wandb_mode(self) -> str:
        """Offline unless asked otherwise: explicit ``mode``, then ``WANDB_MODE``, then online only when the user
        has credentials (``WANDB_API_KEY`` or a wandb entry in ~/.netrc)."""
        if self.mode is not None:
            return self.mode
        if os.environ.get("WANDB_MODE"):
            return os.environ["WANDB_MODE"]
        netrc = Path.home() / ".netrc"
        logged_in = bool(os.environ.get("WANDB_API_KEY")) or (
            netrc.is_file() and "api.wandb.ai" in netrc.read_text(errors="ignore")
        )
        return "online" if logged_in else "offline"


@dataclass
class EvalMPCConfig(Measurement):
    """Closed-loop TTO-MPC of the model being trained (``ttompc.training.callbacks.ClosedLoopEvalCallback``): a
    ``Measurement`` of one horizon on one plant, every ``every_n_val`` validation runs (validation runs, not epochs:
    step-based validation of endless epochs works). Its protocol is checked when the recipe loads, not mid-training.
    """

    problems: int = setting(8, ge=1)
    enabled: bool = False
    every_n_val: int = setting(1, ge=1)

    def __post_init__(self) -> None:
        super().__post_init__()
        self.check_single("callbacks.eval_mpc")


@dataclass
class CallbacksConfig:
    eval_mpc: EvalMPCConfig = field(default_factory=EvalMPCConfig)


@dataclass
class TrainConfig:
    model: ModelConfig = field(default_factory=ModelConfig)
    data: DataConfig = field(default_factory=DataConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    callbacks: CallbacksConfig = field(default_factory=CallbacksConfig)
    # continue from published weights: a zoo name, hf://ORG/NAME[@REV], a planner bundle folder or a Lightning .ckpt.
    # Only a fresh run uses it (a run with checkpoints in out_dir resumes from them); the optimiser starts fresh with
    # its warm-up, the model keeps the source's architecture and normalisation statistics.
    init_from: str | None = None


def load_train_config(path: str | Path | None = None, overrides: Sequence[str] = ()) -> TrainConfig:
    """Load and validate a training recipe; value errors from the sections' checks become ``ConfigError`` too.

    Unless the recipe or the overrides set it, ``model.max_steps`` (the timestep-embedding table) follows the horizon
    N of the first dataset in ``data.paths`` when its manifest is there, so one recipe trains on any scenario
    (``data.context_length`` defaults to that horizon in the data module)."""
    try:
        cfg = load_command_config(TrainConfig, path, overrides)
    except ConfigError:
        raise
    except ValueError as err:
        raise ConfigError(f"invalid config ({path or 'defaults'}): {err}") from None
    horizon = _data_horizon(cfg.data.paths)
    if horizon is not None and "model.max_steps" not in given_keys(path, overrides):
        cfg.model.max_steps = horizon
    return cfg


def _data_horizon(paths: Sequence[str]) -> int | None:
    """N of the first dataset's scenario, or None when it has no readable manifest (``train`` reports that)."""
    if not paths or not Path(paths[0]).is_dir():
        return None
    from ttompc.data.manifests import MANIFEST

    try:
        return int(json.loads((Path(paths[0]) / MANIFEST).read_text())["scenario"]["n_steps"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
