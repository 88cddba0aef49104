"""Crash-safe training checkpoints: a full disk in the middle of a checkpoint write leaves the older checkpoints
intact and no truncated or 0-byte file behind, the same command resumes, damaged checkpoints are skipped and
named, and Ctrl-C surfaces as KeyboardInterrupt (for the CLI's resume hint) after saving the interrupted step."""

from __future__ import annotations

import builtins
import errno
import signal
from pathlib import Path
from typing import Any

import lightning as L
import pytest
from test_training import ToyDataModule, tiny_config

from ttompc.training.checkpoints import checkpoint_step
from ttompc.training.run import train

pytestmark = pytest.mark.slow  # two or three tiny Lightning runs each (~20-40 s on the shared 2-core machine)


class _FullDisk:
    """A file whose writes store half of the bytes, then fail with ENOSPC (what a filling disk does)."""

    def __init__(self, fh: Any) -> None:
        self._fh = fh

    def write(self, data: Any) -> int:
        view = memoryview(data).cast("B")
        self._fh.write(view[: len(view) // 2])
        self._fh.flush()
        raise OSError(errno.ENOSPC, "No space left on device")

    def __getattr__(self, name: str) -> Any:
        return getattr(self._fh, name)

    def __enter__(self) -> _FullDisk:
        return self

    def __exit__(self, *exc: object) -> None:
        self._fh.close()


class _DiskFillsAt(L.Callback):
    """From optimiser step ``step`` on, every binary write in this process hits a full disk."""

    def __init__(self, step: int, monkeypatch: pytest.MonkeyPatch) -> None:
        self.step, self.monkeypatch = step, monkeypatch

    def on_train_batch_end(self, trainer: L.Trainer, *args: object) -> None:
        if trainer.global_step == self.step:
            real_open = builtins.open

            def full_open(file: Any, mode: str = "r", *a: Any, **k: Any) -> Any:
                fh = real_open(file, mode, *a, **k)
                return _FullDisk(fh) if ("w" in mode or "a" in mode) and "b" in mode else fh

            self.monkeypatch.setattr(builtins, "open", full_open)


def test_full_disk_keeps_older_checkpoints_and_the_rerun_resumes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    cfg = tiny_config(out, "trainer.max_steps=9", "logger.kind=none", "trainer.export_planner=false")
    with pytest.raises(OSError) as info:
        train(cfg, ToyDataModule(n=32), callbacks=[_DiskFillsAt(4, monkeypatch)])
    monkeypatch.undo()  # space is free again
    assert info.value.errno == errno.ENOSPC
    assert str(info.value.filename).startswith(str(out / "checkpoints"))  # says which file (and so which disk)
    files = sorted(p.name for p in (out / "checkpoints").iterdir())
    assert files == ["last.ckpt", "step00000003.ckpt"], files  # no temporary, truncated or on_exception file
    assert checkpoint_step(out / "checkpoints" / "last.ckpt") == 3

    # What older versions left behind: a 0-byte on_exception.ckpt and a truncated step file, both newer.
    (out / "checkpoints" / "on_exception.ckpt").write_bytes(b"")
    good = (out / "checkpoints" / "step00000003.ckpt").read_bytes()
    (out / "checkpoints" / "step00000006.ckpt").write_bytes(good[: len(good) // 2])
    capsys.readouterr()
    res = train(cfg, ToyDataModule(n=32))
    err = capsys.readouterr().err
    assert res.start_step == 3 and res.global_step == 9
    assert "skipped checkpoint" in err and "on_exception.ckpt" in err and "step00000006.ckpt" in err
    assert (out / "checkpoints" / "on_exception.ckpt.damaged").exists()
    assert not (out / "checkpoints" / "on_exception.ckpt").exists()


class _CtrlCAt(L.Callback):
    def __init__(self, step: int) -> None:
        self.step = step

    def on_train_batch_end(self, trainer: L.Trainer, *args: object) -> None:
        if trainer.global_step == self.step:
            raise KeyboardInterrupt


def test_ctrl_c_saves_the_step_and_raises_keyboard_interrupt(tmp_path: Path) -> None:
    out = tmp_path / "run"
    cfg = tiny_config(out, "trainer.max_steps=8", "logger.kind=none", "trainer.checkpoint_every_n_steps=100")
    handler = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):  # not Lightning's SystemExit(1): the CLI turns it into exit 130 + hint
        train(cfg, ToyDataModule(n=32), callbacks=[_CtrlCAt(5)])
    assert signal.getsignal(signal.SIGINT) is handler  # Ctrl-C works again afterwards
    assert checkpoint_step(out / "checkpoints" / "on_exception.ckpt") == 5
    res = train(cfg, ToyDataModule(n=32))
    assert res.start_step == 5 and res.global_step == 8
    assert not (out / "checkpoints" / "on_exception.ckpt").exists()  # stale once last.ckpt is newer
