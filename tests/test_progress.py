"""Every long command shows its progress on stderr within seconds of its start and keeps stdout for its result
(``ttompc.progress``); ``TTOMPC_PROGRESS=0`` and ``CI`` turn every bar off. Commands run as a user runs them: in a
subprocess."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import helpers
import mpc_fakes
import pytest
from test_cli import cli_env

from ttompc.parallel import pool_map
from ttompc.progress import Bar, status

TESTS = Path(__file__).resolve().parent
SHORT = mpc_fakes.FreeFlyerShort.name
FIRST_OUTPUT_CPU_S = 5.0  # the "within 5 seconds", in CPU time (see run_watching_stderr)


def run_watching_stderr(argv: list[str], cwd: Path, timeout: float = 600, **env: str) -> tuple[str, str, float]:
    """Run ``python argv`` and return (stdout, stderr, CPU seconds the process had used when its first stderr
    character arrived). CPU time rather than wall time: on the shared 2-core machine a test process niced below
    the training runs may wait many wall-clock seconds for a core, but what it computes before saying something
    is what a user on an idle machine waits for."""
    proc = subprocess.Popen(
        [sys.executable, *argv], cwd=cwd, env={**cli_env(), **env}, stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    assert proc.stderr is not None
    first = os.read(proc.stderr.fileno(), 1)  # unbuffered: communicate() reads the rest from the same descriptor
    fields = Path(f"/proc/{proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
    cpu = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime
    out, err = proc.communicate(timeout=timeout)
    stderr = (first + err).decode()
    assert proc.returncode == 0, stderr
    return out.decode(), stderr, cpu


def frames(stderr: str) -> list[str]:
    """Every redraw of every bar (tqdm separates them with carriage returns) and every line."""
    return [f.strip() for f in stderr.replace("\r", "\n").splitlines() if f.strip()]


def driver(*lines: str) -> list[str]:
    """``python -c`` arguments that register the tests' scenarios, then run the CLI (what a user script does)."""
    code = "\n".join(["import sys", f"sys.path.insert(0, {str(TESTS)!r})", "import mpc_fakes", *lines])
    return ["-c", textwrap.dedent(code)]


# ------------------------------------------------------------------------------------------------ the mechanism
_W: dict[str, Any] = {}


def _keep_ticker(tick: Any) -> None:
    _W["tick"] = tick


def _two_ticks(x: int) -> int:
    _W["tick"]()
    _W["tick"]()
    return x


@pytest.mark.parametrize("workers", [1, 2])
def test_bar_counts_ticks_sent_from_pool_workers(
    workers: int, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    """Work finer than a pool task (episodes of a problem) advances the parent's bar from the worker processes."""
    monkeypatch.setenv("TTOMPC_PROGRESS", "1")
    with Bar(6, "ticks", "episode") as bar:
        assert list(pool_map(_two_ticks, range(3), workers, _keep_ticker, (bar.ticker(),))) == [0, 1, 2]
    captured = capfd.readouterr()
    assert captured.out == ""
    assert frames(captured.err)[-1].startswith("ticks: 100%") and "6/6" in frames(captured.err)[-1], captured.err


def test_fractions_add_up_to_whole_units(monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]) -> None:
    """Episodes in lockstep advance by a share of each step: the bar shows whole episodes, not 0.6666666666666666."""
    monkeypatch.setenv("TTOMPC_PROGRESS", "1")
    with Bar(2, "lockstep", "episode") as bar:
        for _ in range(3):
            bar.update(2 / 3)
    counts = [f.split("| ")[-1].split(" [")[0] for f in frames(capfd.readouterr().err)]
    assert counts[0] == "0/2" and counts[-1] == "2/2" and set(counts) <= {"0/2", "1/2", "2/2"}, counts


def test_bar_redraws_its_elapsed_time_while_an_item_runs(
    monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("TTOMPC_PROGRESS", "1")
    with Bar(1, "slow", "problem"):
        time.sleep(2.5)  # one long item: nothing finishes, the heartbeat still redraws
    shown = frames(capfd.readouterr().err)
    assert any("0/1 [00:02" in f for f in shown), shown


def test_a_broken_stderr_never_stops_or_hangs_the_command(tmp_path: Path) -> None:
    """`ttompc ... 2>&1 | head` closes stderr: tqdm drawing into the broken pipe raised while it held its global
    lock, the heartbeat thread died holding it and the next update waited forever."""
    script = textwrap.dedent(
        """
        import time
        from ttompc.progress import Bar, status
        status("starting")
        with Bar(3, "x") as bar:
            for _ in range(3):
                time.sleep(1.2)  # the heartbeat draws into the broken pipe meanwhile
                bar.update()
        print("done")
        """
    )
    read, write = os.pipe()
    proc = subprocess.Popen(
        [sys.executable, "-c", script],
        cwd=tmp_path,
        env={**cli_env(), "TTOMPC_PROGRESS": "1"},
        stdout=subprocess.PIPE,
        stderr=write,
        text=True,
    )
    os.close(write)
    os.close(read)  # the reader has gone before the first line
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0 and out == "done\n"


@pytest.mark.parametrize("env", [{"TTOMPC_PROGRESS": "0"}, {"CI": "true"}])
def test_switches_turn_bars_status_lines_and_tickers_off(
    env: dict[str, str], monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    for key in ("CI", "TTOMPC_PROGRESS"):
        monkeypatch.delenv(key, raising=False)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    status("ttompc x: loading")
    with Bar(2, "quiet") as bar:
        bar.update()
        bar.ticker()()
    assert capfd.readouterr() == ("", "")


def test_generate_honours_the_progress_switch(tmp_path: Path) -> None:
    """Generation had its own bar that only --no-progress turned off; it follows TTOMPC_PROGRESS like the rest."""
    argv = ["-m", "ttompc.cli", "generate", "problems=2", "shard_size=2", "workers=1", "--splits", "1,0,0"]
    out, err, _ = run_watching_stderr([*argv, f"out={tmp_path / 'off'}"], tmp_path, TTOMPC_PROGRESS="0")
    assert err == "" and json.loads(out)["rows"]["total"] == 4
    out, err, _ = run_watching_stderr([*argv, f"out={tmp_path / 'on'}"], tmp_path, TTOMPC_PROGRESS="1")
    assert "2/2" in frames(err)[-1] and json.loads(out)["rows"]["total"] == 4


def test_zoo_download_honours_the_progress_switch(tmp_path: Path) -> None:
    argv = ["-m", "ttompc.cli", "zoo", "download", "freeflyer-tto-small", "--cache-dir"]
    out, err, _ = run_watching_stderr([*argv, str(tmp_path / "off")], tmp_path, TTOMPC_PROGRESS="0")
    assert err == "" and Path(out.strip(), "config.json").is_file()
    out, err, _ = run_watching_stderr([*argv, str(tmp_path / "on")], tmp_path, TTOMPC_PROGRESS="1")
    assert "model.safetensors" in err and Path(out.strip(), "config.json").is_file()


# ------------------------------------------------------------------------------------------------ long commands
@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return mpc_fakes.tiny_planner().save(tmp_path_factory.mktemp("planner") / "bundle")


@pytest.mark.slow  # two evaluations in subprocesses, one with a spawn pool (~1 min on the loaded machine)
def test_evaluate_shows_progress_on_stderr_at_once(tmp_path: Path, bundle: Path) -> None:
    """`evaluate mpc` printed nothing for minutes: now a line at once, then a bar over episodes that pool workers
    advance as each episode ends (one problem is many episodes); stdout is the table."""
    argv = [
        "evaluate",
        "mpc",
        "--model",
        str(bundle),
        "problems=2",
        "workers=2",
        "max_steps=2",
        "plants=[nominal]",
        "robust_blend=0",
        f"out={tmp_path / 'mpc'}",
    ]
    # TQDM_MININTERVAL=0: every count is drawn, so the granularity below does not depend on how fast episodes end
    out, err, cpu = run_watching_stderr(
        driver(f"from ttompc.cli import main; sys.exit(main({argv!r}))"),
        tmp_path,
        TTOMPC_PROGRESS="1",
        TQDM_MININTERVAL="0",
    )
    assert cpu < FIRST_OUTPUT_CPU_S, (cpu, err)
    shown = frames(err)
    assert shown[0] == f"ttompc evaluate mpc: 2 problems; loading {bundle}", shown
    episodes = [f for f in shown if f.startswith(f"mpc {SHORT}:")]
    assert "0/10" in episodes[0] and "10/10" in episodes[-1], episodes  # 2 problems x (4 baselines + TTO-MPC)
    counts = {f.split("|")[-1].split("[")[0].strip() for f in episodes}
    assert len(counts) > 3, episodes  # counted per episode, not per problem (0, 5 and 10 only)
    assert "\r" not in out and out.startswith("| plant | method |") and "report: " in out

    argv = [
        "evaluate",
        "warmstart",
        "--model",
        str(bundle),
        "problems=2",
        "workers=1",
        "oracle_detours=0",
        f"out={tmp_path / 'ws'}",
    ]
    out, err, cpu = run_watching_stderr(
        driver(f"from ttompc.cli import main; sys.exit(main({argv!r}))"), tmp_path, TTOMPC_PROGRESS="1"
    )
    assert cpu < FIRST_OUTPUT_CPU_S, (cpu, err)
    assert frames(err)[0] == f"ttompc evaluate warmstart: 2 problems; loading {bundle}"
    assert "2/2" in [f for f in frames(err) if f.startswith(f"warmstart {SHORT}:")][-1], err
    assert "\r" not in out and out.startswith("| method | solved |")


@pytest.mark.slow  # one DAgger iteration (one rollout) in a subprocess: ~1 min, far more when the cores are taken
def test_finetune_shows_every_phase_on_stderr_and_names_the_pretrained_model(tmp_path: Path) -> None:
    """Measuring and collecting printed nothing for about 2 of 2.5 minutes, and the decision said "against iteration
    -1". Now each phase has a line and a bar on stderr, the decision names the pretrained model, stdout is JSON."""
    from ttompc.data.manifests import load_manifest
    from ttompc.policy import Planner
    from ttompc.policy.stats import NormStats

    data = tmp_path / "data"
    helpers.tiny_dataset(data, SHORT, 4, (0.5, 0.5, 0.0), shard_size=4)
    planner = mpc_fakes.tiny_planner()
    stats = NormStats.from_dict(load_manifest(data)["norm_stats"])
    source = Planner(planner.model, planner.scenario, stats).save(tmp_path / "pretrained")
    argv = [
        "finetune",
        "--model",
        str(source),
        "dagger.iterations=1",
        "dagger.steps_per_iteration=2",
        "dagger.exploration.horizons=[10]",
        "dagger.exploration.windows=[1,1]",
        "dagger.exploration.window_length=[5,8]",
        "dagger.collect.rollouts=1",
        "dagger.collect.shard_size=1",
        "dagger.collect.workers=1",
        "dagger.collect.val_fraction=0.0",
        "dagger.eval.problems=1",
        "dagger.eval.horizons=[5]",
        "dagger.eval.max_steps=3",
        f"data.paths=[{data}]",
        "data.batch_size=4",
        "data.shuffle_pool=8",
        "data.context_length=10",
        "data.open_loop_fraction=0.5",
        f"trainer.out_dir={tmp_path / 'run'}",
        "trainer.val_check_interval=2",
        "trainer.limit_val_batches=1",
        "trainer.log_every_n_steps=1",
        "trainer.accelerator=cpu",
        "trainer.checkpoint_every_n_steps=1",
        "logger.kind=csv",
    ]
    out, err, cpu = run_watching_stderr(
        driver(f"from ttompc.cli import main; sys.exit(main({argv!r}))"), tmp_path, TTOMPC_PROGRESS="1"
    )
    assert cpu < FIRST_OUTPUT_CPU_S, (cpu, err)
    assert json.loads(out)["best_iteration"] in (-1, 0)
    shown = frames(err)
    assert shown[0] == f"ttompc finetune: loading {source} and Lightning", shown

    def last(prefix: str) -> str:
        return [f for f in shown if f.startswith(prefix)][-1]

    assert "1/1" in last("held-out problems (REL):")
    assert "1/1" in last("measure:")  # the pretrained model, then the candidate
    assert "1/1" in last("collect iteration 0:")
    assert "2/2" in last("train:")  # optimiser steps
    assert "ttompc finetune: measuring the pretrained model (closed-loop TTO-MPC, 1 problem)" in shown
    decision = re.compile(r"ttompc finetune: iteration 0 (kept|rejected) against the pretrained model \(")
    assert any(decision.match(f) for f in shown), shown
    assert "iteration -1" not in err
