"""Experiment loggers (wandb by default, offline unless the user is logged in; CSV; TensorBoard) and a figure
helper that works with any of them. Imported only by training code (it imports Lightning)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ttompc.training.config import LoggerConfig


def _next_version(root: Path) -> str:
    """``session-N``: one more than the sessions already logged under ``root``."""
    existing = [p for p in root.glob("session-*") if p.is_dir()] if root.is_dir() else []
    return f"session-{len(existing)}"


def build_logger(cfg: LoggerConfig, out_dir: Path, config: dict[str, Any]) -> Any:
    """The Lightning logger for ``cfg.kind`` writing under ``out_dir``, with the full config logged; None for
    ``kind: none``."""
    from lightning.pytorch import loggers
    from lightning.pytorch.utilities import rank_zero_only

    if cfg.kind == "none":
        return None
    logger: loggers.Logger
    if cfg.kind == "csv":  # a new version folder per (resumed) session: Lightning would overwrite metrics.csv
        logger = loggers.CSVLogger(save_dir=str(out_dir), name="logs", version=_next_version(out_dir / "logs"))
    elif cfg.kind == "tensorboard":
        logger = loggers.TensorBoardLogger(save_dir=str(out_dir), name="tb", version="")
    else:
        wandb_dir = out_dir / "wandb"
        wandb_dir.mkdir(parents=True, exist_ok=True)
        # A stable id in out_dir lets a resumed run continue the same wandb run.
        id_file = out_dir / "wandb_run_id"
        run_id = id_file.read_text().strip() if id_file.is_file() else None
        logger = loggers.WandbLogger(
            project=cfg.project,
            name=cfg.name,
            save_dir=str(out_dir),
            mode=cfg.wandb_mode(),
            id=run_id,
            resume="allow",
        )
        # Lightning always hands wandb.init an `anonymous` value (None when not asked for), and wandb >= 0.19 warns
        # "The anonymous setting has no effect" for any value: leave the key out so every run starts quietly
        logger._wandb_init.pop("anonymous", None)
        if run_id is None and getattr(rank_zero_only, "rank", 0) == 0:  # set by Lightning at import
            id_file.write_text(str(logger.version) + "\n")
    logger.log_hyperparams(config)
    return logger


def finish_logger(logger: Any) -> None:
    """Close ``logger``'s wandb run, if it is a wandb logger that started one, so that a later run in the same
    process starts (or resumes) its own; any other logger (or None) is left as it is."""
    from lightning.pytorch.loggers import WandbLogger

    if isinstance(logger, WandbLogger) and logger._experiment is not None:
        logger.experiment.finish()


def trajectory_figure(target: np.ndarray, pred: np.ndarray, mask: np.ndarray, title: str = "") -> Any:
    """Position traces (first two state dims) of target vs predicted next states, (k, L, n) each."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 4))
    for i in range(target.shape[0]):
        valid = mask[i] > 0
        line = ax.plot(target[i, valid, 0], target[i, valid, 1], "-", lw=1.5)[0]
        ax.plot(pred[i, valid, 0], pred[i, valid, 1], "--", lw=1.0, color=line.get_color())
    ax.set_xlabel("state[0]")
    ax.set_ylabel("state[1]")
    ax.set_title(f"next states: target (solid) vs predicted (dashed) {title}")
    fig.tight_layout()
    return fig


def log_figure(trainer: Any, key: str, fig: Any, step: int) -> None:
    """Save the figure as PNG under ``<root>/plots/`` and send it to the wandb/TensorBoard logger if any."""
    import matplotlib.pyplot as plt
    from lightning.pytorch import loggers

    plots = Path(trainer.default_root_dir) / "plots"
    plots.mkdir(parents=True, exist_ok=True)
    fig.savefig(plots / f"{key.replace('/', '_')}_{step:07d}.png", dpi=80)
    fig.canvas.draw()
    image = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()  # (H, W, 3) uint8
    plt.close(fig)
    for logger in trainer.loggers:
        if isinstance(logger, loggers.WandbLogger):
            logger.log_image(key=key, images=[image], step=step)
        elif isinstance(logger, loggers.TensorBoardLogger):
            logger.experiment.add_image(key, image, global_step=step, dataformats="HWC")
