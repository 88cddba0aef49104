"""The README's "What you can do" commands run as written.

The bash block is parsed from README.md (so the test breaks when the README drifts), and every command runs in a
subprocess from a scratch folder that looks like the repository root (``recipes/`` linked, a copy of ``zoo/``, a
private cache), in order: what ``generate`` writes is what ``train`` reads, and so on. Each command gets the
``key=value`` settings of its smoke variant appended (a later ``key=value`` wins), which shrink it to seconds.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import TINY_TRAIN

REPO = Path(__file__).resolve().parents[1]

# The smoke variant of each command: settings appended to the README's command line.
SMOKE: dict[str, list[str]] = {
    "solve": [],
    "generate": [
        "problems=4",
        "shard_size=2",
        "workers=1",
        "splits.train=0.5",
        "splits.val=0.25",
        "splits.test=0.25",
        "--no-progress",
    ],
    "train": [
        "trainer.max_steps=2",
        "trainer.val_check_interval=2",
        "trainer.limit_val_batches=1",
        "trainer.checkpoint_every_n_steps=2",
        *TINY_TRAIN,
        "logger.kind=none",
    ],
    "finetune": [
        "dagger.iterations=1",
        "dagger.steps_per_iteration=2",
        "dagger.collect.rollouts=1",
        "dagger.collect.workers=1",
        "dagger.collect.shard_size=1",
        "dagger.exploration.horizons=[10]",
        "dagger.eval.problems=1",
        "dagger.eval.max_steps=3",
        "trainer.val_check_interval=2",
        "trainer.limit_val_batches=1",
        "data.batch_size=4",
        "logger.kind=none",
    ],
    "evaluate warmstart": ["problems=1", "workers=1", "oracle_detours=0"],
    "evaluate mpc": ["problems=1", "workers=1", "horizons=[10]", "max_steps=3", "plants=[nominal]"],
    "zoo list": [],
    "zoo info": [],
    "zoo download": ["--no-progress"],
    "zoo publish": [],
}


def readme_block(language: str, heading: str = "## What you can do") -> str:
    text = (REPO / "README.md").read_text(encoding="utf-8")
    section = text[text.index(heading) :]
    match = re.search(rf"```{language}\n(.*?)```", section, re.DOTALL)
    assert match, f"no {language} block under {heading!r} in README.md"
    return match.group(1)


def readme_commands() -> list[list[str]]:
    """The block's command lines, comments removed, split like a shell would."""
    return [shlex.split(line, comments=True) for line in readme_block("bash").splitlines() if line.strip()]


def smoke_key(argv: list[str]) -> str:
    assert argv[0] == "ttompc", argv
    return " ".join(argv[1:3]) if argv[1] in ("evaluate", "zoo") else argv[1]


def test_every_readme_command_has_a_smoke_variant() -> None:
    """Fast guard: a new or renamed README command needs a smoke rule here (and the slow test runs it)."""
    keys = [smoke_key(argv) for argv in readme_commands()]
    assert keys and set(keys) <= set(SMOKE), set(keys) - set(SMOKE)
    assert set(SMOKE) <= set(keys), f"smoke rules for commands no longer in the README: {set(SMOKE) - set(keys)}"


def test_readme_quickstart_puts_ttompc_on_the_path() -> None:
    """``make demo`` installs into .venv; the commands below it need the venv's ``ttompc`` on PATH."""
    lines = [line.split("#")[0].strip() for line in readme_block("bash", "## Quickstart").splitlines()]
    assert "source .venv/bin/activate" in lines, lines


def test_readme_publish_writes_into_a_user_zoo() -> None:
    """The README's ``zoo publish`` must not edit the tracked ``zoo/`` (its card and ``index.json``): it names its
    own zoo folder and destination, both in the git-ignored ``outputs/``."""
    (argv,) = [a for a in readme_commands() if smoke_key(a) == "zoo publish"]
    ignored = [line.strip() for line in (REPO / ".gitignore").read_text().splitlines()]
    assert "/outputs/" in ignored
    for option in ("--zoo-dir", "--to"):
        assert option in argv and Path(argv[argv.index(option) + 1]).parts[0] == "outputs", (option, argv)


@pytest.mark.slow
def test_readme_commands_run_as_written(tmp_path: Path) -> None:
    (tmp_path / "recipes").symlink_to(REPO / "recipes")
    shutil.copytree(REPO / "zoo", tmp_path / "zoo")
    env = {
        **os.environ,
        "TTOMPC_ZOO": str(tmp_path / "zoo"),
        "TTOMPC_HOME": str(tmp_path / "cache"),
        "TTOMPC_PROGRESS": "0",
        "WANDB_MODE": "offline",
        "WANDB_DIR": str(tmp_path / "wandb"),
        "HF_HUB_OFFLINE": "1",
        "HF_DATASETS_OFFLINE": "1",
    }
    for argv in readme_commands():
        cmd = [sys.executable, "-m", "ttompc.cli", *argv[1:], *SMOKE[smoke_key(argv)]]
        res = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
        assert res.returncode == 0, f"{shlex.join(argv)}\n{res.stdout[-2000:]}\n{res.stderr[-4000:]}"
    # what the README says the commands leave behind
    assert (tmp_path / "outputs" / "solve.png").is_file()
    assert (tmp_path / "data" / "freeflyer-v1" / "manifest.json").is_file()
    assert (tmp_path / "runs" / "freeflyer" / "planner" / "model.safetensors").is_file()
    assert any((tmp_path / "outputs" / "evaluate" / "warmstart-freeflyer").iterdir())
    assert any((tmp_path / "outputs" / "evaluate" / "mpc-freeflyer").iterdir())
    assert any((tmp_path / "outputs" / "evaluate" / "ours").iterdir())  # another config: its own folder
    assert (tmp_path / "outputs" / "my-zoo" / "my-freeflyer.md").is_file()
    assert (tmp_path / "zoo" / "index.json").read_bytes() == (REPO / "zoo" / "index.json").read_bytes()
    assert not (tmp_path / "zoo" / "my-freeflyer.md").exists()


@pytest.mark.slow
def test_readme_python_example_runs(tmp_path: Path) -> None:
    env = {**os.environ, "TTOMPC_HOME": str(tmp_path / "cache"), "HF_HUB_OFFLINE": "1"}
    code = readme_block("python") + "\nassert scp.success, scp.status\n"
    res = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300
    )
    assert res.returncode == 0, res.stderr[-4000:]
    lines = res.stdout.splitlines()  # the two results, one short line each, and the gap to the lower bound
    assert len(lines) == 3 and all(line.startswith("SCPResult(") for line in lines[:2]), res.stdout
    assert lines[2].startswith("SCP from the model: ") and lines[2].endswith("% above the lower bound"), lines[2]
