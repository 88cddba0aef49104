"""The worked example of docs/scenarios.md, end to end through the real CLI, as a user runs it: a scenario file that
is not part of the package (examples/di2d.py) is solved, generated into a dataset by spawned workers, trained on
with the generic recipe, evaluated open loop and closed loop, fine-tuned, published to a temporary zoo and loaded
back by name, each command in a fresh process that finds the scenario from the spec recorded by the previous one.
Kept small: 24 problems, 6 optimiser steps, 1-2 evaluation problems (N = 40 steps)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SPEC = f"{REPO / 'examples' / 'di2d.py'}:DoubleIntegrator2D"

# ~12 commands in fresh processes, two tiny trainings, three spawn pools: minutes on a quiet machine, far longer on
# the shared one (each command imports torch, most of them Lightning)
pytestmark = [pytest.mark.slow, pytest.mark.timeout(3600)]


def ttompc(cwd: Path, *args: str) -> str:
    env = {k: v for k, v in os.environ.items() if k != "TTOMPC_DEBUG"}
    env.update(
        WANDB_MODE="offline",
        HF_HUB_OFFLINE="1",
        HF_DATASETS_OFFLINE="1",
        TTOMPC_PROGRESS="0",
        TTOMPC_ZOO=str(cwd / "zoo"),
        TTOMPC_HOME=str(cwd / "cache"),
    )
    res = subprocess.run(
        [sys.executable, "-m", "ttompc.cli", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=1800
    )
    assert res.returncode == 0, f"ttompc {' '.join(args)} -> {res.returncode}\n{res.stdout[-3000:]}{res.stderr[-3000:]}"
    return res.stdout


def test_example_scenario_from_solve_to_a_published_planner(tmp_path: Path) -> None:
    out = ttompc(tmp_path, "solve", f"scenario={SPEC}", "seed=1", "plot=solve.png")
    assert out.startswith("di2d (v1.0), seed 1") and (tmp_path / "solve.png").is_file()

    ttompc(
        tmp_path,
        "generate",
        f"scenario={SPEC}",
        "problems=24",
        "shard_size=12",
        "out=data/di2d-v1",
        "workers=2",
        "--splits",
        "0.5,0.25,0.25",
        "--no-progress",
    )
    manifest = json.loads((tmp_path / "data/di2d-v1/manifest.json").read_text())
    assert manifest["scenario"]["spec"] == SPEC and manifest["scenario"]["n_steps"] == 40
    assert sum(manifest["counts"]["failures"].values()) == 0

    ttompc(
        tmp_path,
        "train",
        str(REPO / "recipes/generic/tiny.yaml"),
        "data.paths=[data/di2d-v1]",
        "trainer.out_dir=runs/di2d",
        "trainer.max_steps=6",
        "trainer.val_check_interval=3",
        "trainer.limit_val_batches=1",
        "trainer.checkpoint_every_n_steps=3",
        "data.batch_size=8",
        "data.shuffle_pool=16",
    )
    bundle = json.loads((tmp_path / "runs/di2d/planner/config.json").read_text())
    assert bundle["scenario"] == {"name": "di2d", "version": "1.0", "spec": SPEC}
    assert (bundle["model"]["state_dim"], bundle["model"]["control_dim"], bundle["model"]["max_steps"]) == (4, 2, 40)

    ttompc(tmp_path, "evaluate", "warmstart", "--model", "runs/di2d/planner", "problems=2", "workers=2", "out=eval/ws")
    ttompc(
        tmp_path,
        "evaluate",
        "mpc",
        "--model",
        "runs/di2d/planner",
        "problems=1",
        "horizons=[10]",
        "plants=[nominal]",
        "workers=1",
        "out=eval/mpc",
    )
    ttompc(
        tmp_path,
        "finetune",
        "--model",
        "runs/di2d/planner",
        "data.paths=[data/di2d-v1]",
        "data.batch_size=8",
        "data.shuffle_pool=16",
        "dagger.iterations=1",
        "dagger.steps_per_iteration=2",
        "dagger.exploration.horizons=[10]",
        "dagger.collect.rollouts=2",
        "dagger.collect.workers=2",
        "dagger.collect.shard_size=2",
        "dagger.eval.problems=1",
        "trainer.out_dir=runs/di2d-dagger",
        "trainer.limit_val_batches=1",
        "logger.kind=csv",
    )

    ttompc(
        tmp_path,
        "zoo",
        "metrics",
        "--method",
        "TTO",
        "--warmstart",
        "eval/ws/warmstart.json",
        "--mpc",
        "eval/mpc/mpc.json",
        "--out",
        "metrics.json",
    )
    ttompc(
        tmp_path,
        "zoo",
        "publish",
        "runs/di2d/planner",
        "--name",
        "di2d-tto-tiny",
        "--to",
        "zoo/models/di2d-tto-tiny",
        "--card-metrics",
        "metrics.json",
    )
    assert "di2d-tto-tiny" in ttompc(tmp_path, "zoo", "list")
    ttompc(tmp_path, "evaluate", "warmstart", "--model", "di2d-tto-tiny", "problems=1", "workers=1", "out=eval/zoo")
    report = json.loads((tmp_path / "eval/zoo/warmstart.json").read_text())
    assert report["scenario"]["name"] == "di2d" and len(report["problems"]) == 1
