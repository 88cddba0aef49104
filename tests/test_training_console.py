"""What a training run prints: a progress bar with steps, steps/s, ETA and the loss (on by default, off under CI),
and none of Lightning's tips or hardware banners or our own avoidable log lines and warnings."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest
from test_training import ToyDataModule, tiny_config

from ttompc.training.progress import progress_enabled
from ttompc.training.run import train

NOISE = ("Tip", "litlogger", "litmodels", "GPU available", "TPU available", "weights_only", "LeafSpec", "Warning")


@pytest.mark.parametrize(
    ("env", "expected"),
    [
        ({}, True),
        ({"CI": "true"}, False),
        ({"CI": "true", "TTOMPC_PROGRESS": "1"}, True),
        ({"TTOMPC_PROGRESS": "0"}, False),
    ],
)
def test_progress_default_and_switches(monkeypatch: pytest.MonkeyPatch, env: dict[str, str], expected: bool) -> None:
    for key in ("CI", "TTOMPC_PROGRESS"):
        monkeypatch.delenv(key, raising=False)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    assert progress_enabled() is expected


@pytest.mark.slow  # two tiny Lightning runs (~25 s on the shared 2-core machine)
def test_training_shows_steps_rate_eta_and_loss_without_noise(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.delenv("CI", raising=False)
    monkeypatch.delenv("TTOMPC_PROGRESS", raising=False)
    out = tmp_path / "run"
    cfg = tiny_config(out, "trainer.max_steps=6", "logger.kind=csv", "trainer.export_planner=false")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        train(cfg, ToyDataModule(n=32))
    captured = capfd.readouterr()
    frames = captured.out.replace("\r", "\n").splitlines()
    bars = [f for f in frames if f.startswith("train:")]
    assert bars, captured.out
    last = bars[-1]
    assert "6/6" in last and "it/s" in last and "train/loss=" in last, last  # steps, rate, loss
    assert any("<" in f and "/6 [" in f for f in bars)  # elapsed<remaining: the ETA
    for word in NOISE:
        assert word not in captured.out + captured.err, (word, captured.err)
    assert [str(w.message) for w in caught] == []

    # resumed mid-epoch: the bar continues at the resumed step, towards the new max_steps
    resumed = tiny_config(out, "trainer.max_steps=8", "logger.kind=csv", "trainer.export_planner=false")
    train(resumed, ToyDataModule(n=32))
    frames = capfd.readouterr().out.replace("\r", "\n").splitlines()
    bars = [f for f in frames if f.startswith("train:")]
    assert bars and "6/8" in bars[0] and "8/8" in bars[-1], bars
