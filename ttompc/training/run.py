"""``train(cfg)``: one pre-training run from a ``TrainConfig``, and ``build_trainer``, the Lightning Trainer that
DAgger fine-tuning (``ttompc.finetune``) shares.

Resumable by construction: checkpoints go to ``<out_dir>/checkpoints/`` with ``last.ckpt`` refreshed every
``checkpoint_every_n_steps`` and at the end (``on_exception.ckpt`` when fit raises, e.g. Ctrl-C); every write is
atomic (``ttompc.training.checkpoints``), and a run whose ``out_dir`` already holds checkpoints continues from the
newest one that loads (optimiser, scheduler, loop counters) instead of restarting from step 0.
Multi-device runs go through Lightning strategies (``trainer.devices=2 trainer.strategy=ddp``). After training,
rank 0 exports a ``Planner`` bundle to ``<out_dir>/planner/``.
"""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ttompc.config import ConfigError, to_container
from ttompc.policy.config import ModelConfig
from ttompc.training.config import OptimConfig, TrainConfig, TrainerConfig

if TYPE_CHECKING:
    from ttompc.policy import Planner


@dataclass
class TrainResult:
    out_dir: Path
    last_checkpoint: Path
    planner_dir: Path | None
    start_step: int  # global step the run started from (> 0 when resumed)
    global_step: int
    metrics: dict[str, float]


def build_trainer(
    t: TrainerConfig,
    optim: OptimConfig,
    out: Path,
    logger: Any,
    *,
    callbacks: list[Any] | None = None,
    enable_checkpointing: bool = True,
) -> Any:
    """The Lightning Trainer of a recipe's ``trainer``/``optim`` sections (pre-training and DAgger share it; the
    step budget, ``max_steps``/``max_epochs``, and the sanity validation steps are ``t``'s). A
    ``precision`` of ``auto`` is resolved for the machine (``ttompc.training.precision``); its checkpoints record the
    precision that ran (``checkpoint["precision"]``). It sets no ``gradient_clip_val``: the module clips to
    ``optim.grad_clip`` itself (``TrajectoryTransformerModule.configure_gradient_clipping``)."""
    import lightning as L

    from ttompc.training.checkpoints import AtomicCheckpointIO
    from ttompc.training.precision import RecordPrecision, resolve_precision
    from ttompc.training.progress import StepProgressBar, progress_enabled, quiet_lightning

    quiet_lightning()
    progress = progress_enabled()
    vci = t.val_check_interval
    return L.Trainer(
        max_steps=t.max_steps,
        max_epochs=t.max_epochs,
        val_check_interval=int(vci) if vci > 1 else vci,
        limit_val_batches=int(t.limit_val_batches) if t.limit_val_batches > 1 else t.limit_val_batches,
        check_val_every_n_epoch=None if vci > 1 else 1,
        accelerator=t.accelerator,
        devices=t.devices,
        num_nodes=t.num_nodes,
        strategy=t.strategy,
        precision=resolve_precision(t.precision, accelerator=t.accelerator, strategy=t.strategy),
        accumulate_grad_batches=optim.accumulate,
        log_every_n_steps=t.log_every_n_steps,
        num_sanity_val_steps=t.num_sanity_val_steps,
        default_root_dir=str(out),
        logger=logger if logger is not None else False,
        callbacks=[*(callbacks or []), RecordPrecision(), *([StepProgressBar()] if progress else [])],
        plugins=[AtomicCheckpointIO()],
        enable_checkpointing=enable_checkpointing,
        enable_progress_bar=progress,
        enable_model_summary=False,
    )


def train(cfg: TrainConfig, datamodule: Any = None, callbacks: Sequence[Any] = ()) -> TrainResult:
    """Train according to ``cfg``. ``datamodule`` defaults to ``TrajectoryDataModule(cfg.data)``; any
    LightningDataModule that follows the batch contract of ``ttompc.training.module`` and exposes ``stats``
    (NormStats) and ``scenario_name`` after ``setup("fit")`` works. ``callbacks`` are added to the Trainer's (e.g.
    the closed-loop evaluation configured by ``cfg.callbacks.eval_mpc``).

    Checked first, as ``ttompc train`` checks them, and refused in its words (``ConfigError``/``UserError``,
    ``ttompc.training.preflight``): devices this machine lacks, datasets that are missing, unfinished or of mixed
    scenarios, and a ``trainer.out_dir`` that is not this run's — a folder of other files, or checkpoints of another
    scenario, data set or architecture (with a ``datamodule``: another scenario or architecture), which would
    otherwise resume the wrong model."""
    from ttompc.ranges import check_devices
    from ttompc.training.preflight import claim_run, prepare_run

    own_data = datamodule is None
    if own_data:
        prepare_run(cfg)
    else:
        check_devices(cfg)
    import lightning as L
    from lightning.pytorch.callbacks import LearningRateMonitor, ModelCheckpoint

    from ttompc.policy import Planner
    from ttompc.scenarios import get_scenario
    from ttompc.training.checkpoints import (
        ExceptionCheckpoint,
        checkpoint_step,
        exception_checkpoint,
        last_checkpoint,
        resume_checkpoint,
    )
    from ttompc.training.loggers import build_logger, finish_logger
    from ttompc.training.module import SaveLastCheckpoint, build_module

    L.seed_everything(cfg.trainer.seed, workers=True, verbose=False)
    out = Path(cfg.trainer.out_dir)
    if datamodule is None:
        from ttompc.data.datamodule import TrajectoryDataModule

        datamodule = TrajectoryDataModule(cfg.data)
    datamodule.setup("fit")  # stats and scenario are needed to build the model (setup must be idempotent)
    scenario = get_scenario(datamodule.scenario_name)
    if not own_data:  # the datasets' runs were claimed by prepare_run; this data is known by its scenario
        claim_run(
            cfg, [], {"name": scenario.name, "state_dim": scenario.state_dim, "control_dim": scenario.control_dim}
        )
    out.mkdir(parents=True, exist_ok=True)  # only once the data loads: a typo in data.paths leaves nothing behind
    # The data fixes the token dimensions; the recipe fixes everything else.
    model_cfg = replace(cfg.model, state_dim=scenario.state_dim, control_dim=scenario.control_dim)
    if cfg.optim.trainable == "value" and not cfg.init_from:
        raise ConfigError("optim.trainable=value trains a value output on a frozen policy: give init_from=MODEL")
    source = _init_source(cfg.init_from, model_cfg, scenario.name) if cfg.init_from else None
    if source is not None:  # the source's input scaling goes with its weights
        datamodule.use_stats(source.stats)
    cfg = replace(cfg, model=model_cfg)
    recipe = to_container(cfg)
    module = build_module(
        model_cfg,
        cfg.optim,
        scenario,
        datamodule.stats,
        recipe=cfg,
        plot_trajectories=cfg.logger.plot_trajectories,
        backend=cfg.callbacks.eval_mpc.settings.backend,  # what the run's closed loop solves with
    )
    logger = build_logger(cfg.logger, out, recipe)
    ckpt_dir = out / "checkpoints"
    all_callbacks: list[Any] = [
        *callbacks,
        ModelCheckpoint(
            dirpath=ckpt_dir,
            filename="step{step:08d}",
            auto_insert_metric_name=False,
            monitor="step",
            mode="max",
            save_top_k=cfg.trainer.keep_checkpoints,
            every_n_train_steps=cfg.trainer.checkpoint_every_n_steps,
        ),
        ExceptionCheckpoint(exception_checkpoint(out)),
        SaveLastCheckpoint(last_checkpoint(out), cfg.trainer.checkpoint_every_n_steps),
    ]
    if logger is not None:
        all_callbacks.append(LearningRateMonitor(logging_interval="step"))
    if cfg.callbacks.eval_mpc.enabled:
        from ttompc.training.callbacks import ClosedLoopEvalCallback

        all_callbacks.append(ClosedLoopEvalCallback.from_config(cfg.callbacks.eval_mpc, scenario.name))
    t = cfg.trainer
    trainer = build_trainer(t, cfg.optim, out, logger, callbacks=all_callbacks)
    found = resume_checkpoint(out) if t.resume else None
    resume_from, start_step = found if found else (None, 0)
    if resume_from is not None and trainer.is_global_zero:
        print(f"ttompc: resuming from {resume_from} (step {start_step})", file=sys.stderr)
    elif source is not None:
        load_source_weights(module.model, source.model.state_dict())
        if trainer.is_global_zero:
            print(f"ttompc: starting from the weights of {cfg.init_from} (fresh optimiser)", file=sys.stderr)
    fit(trainer, module, datamodule, resume_from)
    finish_logger(logger)
    exception_checkpoint(out).unlink(missing_ok=True)  # last.ckpt is newer; a stale one would only confuse
    # Read the outcome from the checkpoint: with spawn-based strategies the workers, not this process, trained.
    global_step = checkpoint_step(last_checkpoint(out))
    planner_dir = None
    if trainer.is_global_zero and t.export_planner:
        planner = Planner.from_pretrained(last_checkpoint(out), scenario)
        planner.extra["source"] = "ttompc train"
        if cfg.optim.trainable == "value" and source is not None:
            planner.extra.update(value_lineage(source, str(cfg.init_from)))
        planner_dir = planner.save(out / "planner")
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if getattr(v, "numel", lambda: 1)() == 1}
    return TrainResult(out, last_checkpoint(out), planner_dir, start_step, global_step, metrics)


def value_lineage(source: Any, name: str) -> dict[str, Any]:
    """What a bundle whose value output was added to ``source`` (published as ``name``) inherits: the policy is the
    source's, so its conditioning scale; the source as its parent (``value_added_to``), and for a fine-tuned source
    also as the model it was fine-tuned from (its kind stays FT-TTO, the card's base model is the source)."""
    out: dict[str, Any] = {"rtg_scale": source.rtg_scale, "value_added_to": name}
    if "finetuned_from" in source.extra:
        out["finetuned_from"] = name
    return out


def load_source_weights(model: Any, state: dict[str, Any]) -> None:
    """``init_from``'s weights into ``model``; a value output the source lacks (``model.value_width`` added to a
    published model) or has in another shape (``value_form``/``value_width``/``value_rank`` changed: a new value
    output for the same policy) keeps its fresh initialisation, any other mismatch raises ``ConfigError``."""
    if model.value_head is None and any(k.startswith("value_head.") for k in state):
        raise ConfigError("init_from has a value output: keep model.value_width as in its bundle")
    mine = {k: v.shape for k, v in model.state_dict().items() if k.startswith("value_head.")}
    theirs = {k: v.shape for k, v in state.items() if k.startswith("value_head.")}
    if mine != theirs:  # another value output: the policy's weights only
        state = {k: v for k, v in state.items() if not k.startswith("value_head.")}
    missing, unexpected = model.load_state_dict(state, strict=False)
    if unexpected or any(not k.startswith("value_head.") for k in missing):
        raise ConfigError(f"init_from's weights do not fit the model: missing {missing}, unexpected {unexpected}")


# the fields that shape the weights: a continued run must keep them
_ARCHITECTURE = ("layout", "n_embd", "n_layer", "n_head", "mlp_ratio", "max_steps", "bias", "activation")


def _init_source(init_from: str, model: ModelConfig, scenario: str) -> Planner:
    """The planner a fresh run continues from; its scenario and architecture must be the recipe's."""
    from ttompc.policy import Planner

    source = Planner.from_pretrained(init_from)
    if source.scenario.name != scenario:
        raise ConfigError(f"init_from={init_from} is a {source.scenario.name} model, the data is {scenario}")
    for name in _ARCHITECTURE:
        mine, theirs = getattr(model, name), getattr(source.model.cfg, name)
        if mine != theirs:
            raise ConfigError(
                f"model.{name}={mine} differs from init_from's {theirs}: the weights fix the architecture "
                f"(use a recipe with model.{name}: {theirs})"
            )
    return source


def fit(trainer: Any, module: Any, datamodule: Any, ckpt_path: Path | None) -> None:
    """``trainer.fit`` where Ctrl-C stays a ``KeyboardInterrupt`` (the CLI prints how to resume): Lightning turns it
    into ``sys.exit(1)`` after the exception checkpoint is written, and ignores Ctrl-C from then on."""
    sigint = signal.getsignal(signal.SIGINT)
    try:
        trainer.fit(module, datamodule=datamodule, ckpt_path=str(ckpt_path) if ckpt_path else None)
    except SystemExit as err:
        if trainer.interrupted:
            raise KeyboardInterrupt from err
        raise
    finally:
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, sigint)
