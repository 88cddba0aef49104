"""What training shows on the console: one step progress bar on stderr (steps/s, ETA, loss), no Lightning tips.

The bar follows ``ttompc.progress``: on stderr like every command's progress, so stdout carries only the final JSON
(``ttompc train ... | python -m json.tool``); on by default, ``TTOMPC_PROGRESS=0`` turns it off and it is off when
``CI`` is set, unless ``TTOMPC_PROGRESS=1``.
"""

from __future__ import annotations

import logging
import warnings
from typing import Any

from lightning.pytorch.callbacks import TQDMProgressBar
from lightning.pytorch.callbacks.progress.tqdm_progress import Tqdm

from ttompc.progress import STDERR, progress_enabled

__all__ = ["StepProgressBar", "progress_enabled", "quiet_lightning"]  # build_trainer takes the switch from here


def quiet_lightning() -> None:
    """Hide Lightning's info lines (hardware summary, tips about other products); warnings still show."""
    for name in ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero"):
        logging.getLogger(name).setLevel(logging.WARNING)
    # Lightning 2.6 calls a torch.utils._pytree API that torch 2.13 deprecates, once per batch: not ours to fix
    # train() resumes into the checkpoint folder on purpose
    warnings.filterwarnings("ignore", message=r"Checkpoint directory .* exists and is not empty")
    warnings.filterwarnings("ignore", message=r".*isinstance\(treespec, LeafSpec\)", category=FutureWarning)


class StepProgressBar(TQDMProgressBar):
    """Counts optimiser steps towards ``max_steps``, from the resumed step on, on stderr; no other bar.

    Our data is one endless epoch, so Lightning's per-epoch batch bar has no total (no ETA) and restarts at 0 on
    resume; this bar shows ``step/max_steps``, steps/s over this session, the ETA and the logged losses. Lightning's
    own bars ("Training", "Epoch 0", "Validation DataLoader 0", the sanity check) are not drawn: validation shows as
    ``train (validating)`` on this bar.
    """

    DESCRIPTION = "train"

    def init_train_tqdm(self) -> Tqdm:
        steps = self.trainer.max_steps
        return Tqdm(
            desc=self.DESCRIPTION,
            total=steps if steps > 0 else None,
            initial=self.trainer.global_step if steps > 0 else 0,  # the rate counts this session's steps only
            position=2 * self.process_position,
            disable=self.is_disabled,
            leave=True,
            dynamic_ncols=True,
            file=STDERR,
            smoothing=0,
            bar_format=self.BAR_FORMAT,
        )

    def init_validation_tqdm(self) -> Tqdm:
        return Tqdm(disable=True)

    def init_sanity_tqdm(self) -> Tqdm:
        return Tqdm(disable=True)

    def on_train_epoch_start(self, trainer: Any, *args: Any) -> None:
        if trainer.max_steps <= 0:  # epoch-based run: Lightning's batch count of each epoch, on our bar
            super().on_train_epoch_start(trainer, *args)
        # else the bar counts steps across epochs (it starts at the resumed step: init_train_tqdm)

    def on_train_batch_end(self, trainer: Any, pl_module: Any, outputs: Any, batch: Any, batch_idx: int) -> None:
        if trainer.max_steps <= 0:
            super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)
            return
        bar, step = self.train_progress_bar, trainer.global_step
        if bar is not None and self._should_update(step, trainer.max_steps) and step != bar.n:
            bar.n = step
            bar.set_postfix(self.get_metrics(trainer, pl_module))  # also redraws

    def on_validation_start(self, trainer: Any, pl_module: Any) -> None:
        super().on_validation_start(trainer, pl_module)
        self._describe(trainer, f"{self.DESCRIPTION} (validating)")

    def on_validation_end(self, trainer: Any, pl_module: Any) -> None:
        super().on_validation_end(trainer, pl_module)
        self._describe(trainer, self.DESCRIPTION)

    def _describe(self, trainer: Any, text: str) -> None:
        if self._train_progress_bar is not None and not trainer.sanity_checking and trainer.state.fn == "fit":
            self.train_progress_bar.set_description(text)

    def get_metrics(self, trainer: Any, pl_module: Any) -> dict[str, Any]:
        metrics = super().get_metrics(trainer, pl_module)
        metrics.pop("v_num", None)  # the logger's version number is noise here
        return metrics
