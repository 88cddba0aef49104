"""What a training run prints: one progress bar on stderr with steps, steps/s, ETA and the loss (on by default, off
under CI), none of Lightning's own bars, tips or hardware banners or our own avoidable log lines and warnings, and on
stdout only the final JSON."""

from __future__ import annotations

import json
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
from helpers import TINY_TRAIN
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
    assert captured.out == "", captured.out  # progress goes to stderr: stdout is the command's result
    frames = captured.err.replace("\r", "\n").splitlines()
    bars = [f for f in frames if f.startswith("train:")]
    assert bars, captured.err
    last = bars[-1]
    assert "6/6" in last and "it/s" in last and "train/loss=" in last, last  # steps, rate, loss
    assert any("<" in f and "/6 [" in f for f in bars)  # elapsed<remaining: the ETA
    assert any(f.startswith("train (validating):") for f in frames)  # validation shows on our bar, not its own
    for lightning_bar in ("Training", "Epoch 0", "Validation", "Sanity"):
        assert lightning_bar not in captured.err, lightning_bar
    for word in NOISE:
        assert word not in captured.out + captured.err, (word, captured.err)
    assert [str(w.message) for w in caught] == []

    # resumed mid-epoch: the bar continues at the resumed step, towards the new max_steps
    resumed = tiny_config(out, "trainer.max_steps=8", "logger.kind=csv", "trainer.export_planner=false")
    train(resumed, ToyDataModule(n=32))
    frames = capfd.readouterr().err.replace("\r", "\n").splitlines()
    bars = [f for f in frames if f.startswith("train:")]
    assert bars and "6/8" in bars[0] and "8/8" in bars[-1], bars


@pytest.mark.slow  # a dataset and a 4-step run with wandb (offline) in subprocesses (~1 min on the loaded machine)
def test_train_command_stdout_is_json_and_its_one_bar_is_on_stderr(tmp_path: Path) -> None:
    """`ttompc train ... | python -m json.tool` failed on Lightning's and our bars on stdout, and every wandb run
    warned that "the anonymous setting has no effect"."""
    from test_progress import FIRST_OUTPUT_CPU_S, frames, run_watching_stderr

    data = tmp_path / "data"
    run_watching_stderr(
        [
            "-m",
            "ttompc.cli",
            "generate",
            "problems=4",
            "shard_size=2",
            "workers=1",
            "--splits",
            "0.5,0.25,0.25",
            f"out={data}",
        ],
        tmp_path,
        TTOMPC_PROGRESS="0",
    )
    argv = [
        "-m",
        "ttompc.cli",
        "train",
        str(Path(__file__).resolve().parents[1] / "recipes/freeflyer/tiny.yaml"),
        f"data.paths=[{data}]",
        f"trainer.out_dir={tmp_path / 'run'}",
        *TINY_TRAIN,
        "trainer.max_steps=4",
        "trainer.val_check_interval=2",
        "trainer.limit_val_batches=1",
        "trainer.export_planner=false",
        "logger.kind=wandb",
    ]
    out, err, cpu = run_watching_stderr(argv, tmp_path, TTOMPC_PROGRESS="1", WANDB_MODE="offline")
    assert cpu < FIRST_OUTPUT_CPU_S, (cpu, err)
    piped = subprocess.run([sys.executable, "-m", "json.tool"], input=out, capture_output=True, text=True)
    assert piped.returncode == 0 and json.loads(out)["global_step"] == 4, out
    shown = frames(err)
    assert shown[0] == "ttompc train: loading Lightning and the data", shown
    bars = [f for f in shown if f.startswith("train:")]
    assert bars and "4/4" in bars[-1], shown
    for lightning_bar in ("Training", "Epoch 0", "Validation", "Sanity"):
        assert lightning_bar not in err, (lightning_bar, err)
    assert "anonymous" not in err, err


def test_help_and_print_config_say_which_max_steps_is_which(capsys: pytest.CaptureFixture[str]) -> None:
    """model.max_steps (trajectory length the model takes) and trainer.max_steps (optimiser steps) share a name."""
    from ttompc.cli import main

    recipe = str(Path(__file__).resolve().parents[1] / "recipes/freeflyer/tiny.yaml")
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "model.max_steps is the longest trajectory the model takes, in control steps" in text
    assert "trainer.max_steps is how long to train, in optimiser steps" in text
    assert main(["train", recipe, "--print-config"]) == 0
    captured = capsys.readouterr()
    cfg = json.loads(captured.out)  # stdout stays the config alone
    assert cfg["model"]["max_steps"] == 100 and cfg["trainer"]["max_steps"] == 2000
    assert "model.max_steps is the longest trajectory" in captured.err
    assert "trainer.max_steps is how long to train" in captured.err
