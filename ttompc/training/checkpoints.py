"""Crash-safe training checkpoints: atomic writes, and resuming from the newest checkpoint that still loads.

Every checkpoint the Trainer writes (``last.ckpt``, ``step<N>.ckpt``, ``on_exception.ckpt``) goes through
``AtomicCheckpointIO``: serialised in memory, written to a hidden temporary file in the same folder, flushed and
renamed over the target. A full disk or a kill therefore leaves the previous file intact and no 0-byte or truncated
checkpoint behind. ``resume_checkpoint`` still copes with damaged files from elsewhere (a copy cut short, an older
version of ttompc): it tries the checkpoints newest first and moves the ones that do not load aside
(``<name>.damaged``), saying so.
"""

from __future__ import annotations

import io
import os
import sys
from pathlib import Path
from typing import Any

import lightning as L
import torch
from lightning.pytorch.plugins.io import TorchCheckpointIO

EXCEPTION_CKPT = "on_exception"  # written by ExceptionCheckpoint when fit raises (Ctrl-C too); removed on success


def checkpoint_dir(out_dir: str | Path) -> Path:
    return Path(out_dir) / "checkpoints"


def last_checkpoint(out_dir: str | Path) -> Path:
    return checkpoint_dir(out_dir) / "last.ckpt"


def exception_checkpoint(out_dir: str | Path) -> Path:
    return checkpoint_dir(out_dir) / f"{EXCEPTION_CKPT}.ckpt"


class AtomicCheckpointIO(TorchCheckpointIO):
    """``TorchCheckpointIO`` whose saves are all-or-nothing (temporary file + ``os.replace``)."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: Any, storage_options: Any | None = None) -> None:
        target = Path(path)
        target.parent.mkdir(parents=True, exist_ok=True)
        buffer = io.BytesIO()
        torch.save(checkpoint, buffer)
        write_atomic(target, buffer.getbuffer())


class ExceptionCheckpoint(L.Callback):
    """Save ``on_exception.ckpt`` when fit raises (Ctrl-C included) so the interrupted steps are not lost.

    Unlike Lightning's ``OnExceptionCheckpoint`` it does not make ``fit(ckpt_path=None)`` look for a "last"
    checkpoint (``train`` chooses the resume checkpoint itself), and a failing save (the disk that is full) is
    reported without hiding the original exception.
    """

    def __init__(self, path: Path) -> None:
        self.path = path

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        if trainer.global_step == 0:
            return
        try:
            trainer.save_checkpoint(self.path, weights_only=False)
        except Exception as err:
            print(f"ttompc: could not save {self.path} ({err}); older checkpoints are kept", file=sys.stderr)


def write_atomic(target: Path, data: bytes | memoryview) -> None:
    """Write ``data`` to ``target`` via a temporary sibling; on failure the temporary file is removed and the
    ``OSError`` names ``target`` (a bare ``write`` error does not say which file)."""
    tmp = target.with_name(f".{target.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException as err:
        tmp.unlink(missing_ok=True)
        if isinstance(err, OSError) and not err.filename:
            raise OSError(err.errno, err.strerror, str(target)) from err
        raise


def checkpoint_step(path: Path) -> int:
    """The global step stored in a checkpoint (loaded with ``weights_only=True``: nothing is unpickled)."""
    return int(torch.load(path, map_location="cpu", weights_only=True).get("global_step", 0))


def resume_checkpoint(out_dir: str | Path) -> tuple[Path, int] | None:
    """The newest checkpoint of ``out_dir`` that loads, with its global step; None when there is none.

    Candidates are ``last.ckpt``, ``on_exception.ckpt`` and ``step<N>.ckpt``, tried by modification time, newest
    first. Files that fail to load are renamed to ``<name>.damaged`` (kept for inspection, no longer in the way) and
    reported on stderr.
    """
    folder = checkpoint_dir(out_dir)
    if not folder.is_dir():
        return None
    candidates = sorted(folder.glob("*.ckpt"), key=lambda p: p.stat().st_mtime, reverse=True)
    for path in candidates:
        try:
            step = checkpoint_step(path)
        except Exception as err:  # truncated zip, empty file, unpickling refused: all mean "cannot resume from it"
            damaged = path.with_name(path.name + ".damaged")
            os.replace(path, damaged)
            print(
                f"ttompc: skipped checkpoint {path} (does not load: {type(err).__name__}); moved it to {damaged.name}",
                file=sys.stderr,
            )
            continue
        return path, step
    return None
