"""What training shows on the console: a step progress bar (steps/s, ETA, loss) and no Lightning tips.

The bar is on by default; ``TTOMPC_PROGRESS=0`` turns it off and it is off when ``CI`` is set (CI logs do not
redraw lines), unless ``TTOMPC_PROGRESS=1``.
"""

from __future__ import annotations

import logging
import os
import warnings
from typing import Any

from lightning.pytorch.callbacks import TQDMProgressBar


def progress_enabled() -> bool:
    setting = os.environ.get("TTOMPC_PROGRESS", "").strip().lower()
    if setting:
        return setting not in ("0", "false", "no", "off")
    return not os.environ.get("CI")


def quiet_lightning() -> None:
    """Hide Lightning's info lines (hardware summary, tips about other products); warnings still show."""
    for name in ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero"):
        logging.getLogger(name).setLevel(logging.WARNING)
    # Lightning 2.6 calls a torch.utils._pytree API that torch 2.13 deprecates, once per batch: not ours to fix
    # train() resumes into the checkpoint folder on purpose
    warnings.filterwarnings("ignore", message=r"Checkpoint directory .* exists and is not empty")
    warnings.filterwarnings("ignore", message=r".*isinstance\(treespec, LeafSpec\)", category=FutureWarning)


class StepProgressBar(TQDMProgressBar):
    """Counts optimiser steps towards ``max_steps``, from the resumed step on.

    Our data is one endless epoch, so Lightning's per-epoch batch bar has no total (no ETA) and restarts at 0 on
    resume; this bar shows ``step/max_steps``, steps/s over this session, the ETA and the logged losses.
    """

    def on_train_start(self, trainer: Any, pl_module: Any) -> None:
        super().on_train_start(trainer, pl_module)
        self._count_steps(trainer)  # a run resumed mid-epoch gets no on_train_epoch_start first

    def on_train_epoch_start(self, trainer: Any, *args: Any) -> None:
        super().on_train_epoch_start(trainer, *args)
        self._count_steps(trainer)

    def _count_steps(self, trainer: Any) -> None:
        if trainer.max_steps > 0:
            bar = self.train_progress_bar
            bar.reset(total=trainer.max_steps)
            bar.initial = bar.n = trainer.global_step  # the rate counts this session's steps only
            bar.set_description("train")

    def on_train_batch_end(self, trainer: Any, pl_module: Any, outputs: Any, batch: Any, batch_idx: int) -> None:
        if trainer.max_steps <= 0:
            super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)
            return
        bar, step = self.train_progress_bar, trainer.global_step
        if bar is not None and self._should_update(step, trainer.max_steps) and step != bar.n:
            bar.n = step
            bar.set_postfix(self.get_metrics(trainer, pl_module))  # also redraws

    def get_metrics(self, trainer: Any, pl_module: Any) -> dict[str, Any]:
        metrics = super().get_metrics(trainer, pl_module)
        metrics.pop("v_num", None)  # the logger's version number is noise here
        return metrics
