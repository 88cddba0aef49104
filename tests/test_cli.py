"""The CLI's one error path, run as a user runs it (a subprocess): a user error is one line on stderr naming the
problem and what to do, exit code 2, no traceback and nothing created; Ctrl-C and a full disk say how to resume;
a closed pipe is quiet. None of these commands imports Lightning."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from cli_batch import read_only_folder

REPO = Path(__file__).resolve().parents[1]
TINY = str(REPO / "recipes/freeflyer/tiny.yaml")


def cli_env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "TTOMPC_DEBUG"}
    env.update(WANDB_MODE="offline", HF_HUB_OFFLINE="1", HF_DATASETS_OFFLINE="1", TTOMPC_PROGRESS="0", **extra)
    return env


def ttompc(*args: str, cwd: Path, timeout: float = 120, **env: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ttompc.cli", *args],
        cwd=cwd,
        env=cli_env(**env),
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def assert_user_error(res: subprocess.CompletedProcess[str], *needles: str) -> str:
    """Exit 2, exactly one line on stderr, no traceback; returns the line."""
    assert res.returncode == 2, (res.returncode, res.stderr)
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in res.stderr, res.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (["solve", "--scenario", "nope"], ["unknown scenario 'nope'", "freeflyer, quadrotor, rpod"]),
        (["solve", "scenario=nope"], ["unknown scenario 'nope'"]),
        (["solve", "--backend", "gurobi"], ["unknown solver backend 'gurobi'", "clarabel", "riccati", "piqp"]),
        (["solve", "--seed", "-1"], ["invalid seed=-1: must be >= 0"]),
        (["solve", "sead=3"], ["unknown setting 'sead'", "valid keys: scenario, seed"]),
        (["generate", "--scenario", "nope", "--out", "out"], ["unknown scenario 'nope'"]),
        (["generate", "problemz=3", "out=out"], ["unknown setting 'problemz'", "problems"]),
        (["generate", "splits.tran=0.5", "out=out"], ["unknown setting 'splits.tran'", "under 'splits': train"]),
        (["generate", "problems=many", "out=out"], ["'problems'", "could not be converted"]),
        (["generate", "--seed", "-3", "--out", "out"], ["invalid seed=-3: must be >= 0"]),
        (["generate", "--backend", "nope", "--out", "out"], ["unknown solver backend 'nope'"]),
        (["generate", "missing.yaml", "out=out"], ["recipe not found: missing.yaml"]),
        (["generate", "problems=0", "out=out"], ["invalid problems=0: must be >= 1"]),
        (["generate", "--problems", "-3", "--out", "out"], ["invalid problems=-3: must be >= 1"]),
        (["generate", "shard_size=0", "out=out"], ["invalid shard_size=0: must be >= 1"]),
        (["generate", "solver=nope:solve", "out=out"], ["solver=nope:solve: cannot import nope", "solve_problem"]),
        (["generate", "solver=ttompc.solvers.scp:nope", "out=out"], ["ttompc.solvers.scp has no function 'nope'"]),
        (["generate", "solver=nocolon", "out=out"], ["solver='nocolon' is not 'module:function'"]),
        (
            ["train", TINY, "data.paths=[no/such/data]", "trainer.out_dir=out"],
            ["dataset folder no/such/data does not exist", "ttompc generate"],
        ),
        (["train", TINY, "optim.learning_rate=1"], ["'optim.learning_rate'"]),
        (
            [
                "train",
                str(REPO / "recipes/freeflyer/tiny.yaml"),
                f"data.paths=[{REPO / 'recipes'}]",
                "trainer.out_dir=o",
            ],
            ["is not a dataset made by `ttompc generate` (no manifest.json)"],
        ),
        (["finetune", str(REPO / "recipes/freeflyer/finetune.yaml")], ["--model"]),
        (  # an MPC setting that does not exist (here the removed finish cost) is named with the valid ones
            ["evaluate", "mpc", "--scenario", "freeflyer", "mpc.finish=1"],
            [
                "unknown setting 'finish'",
                "valid keys: mode, end_horizon, track, terminal, rtg_mode, reuse, end_shift, rti, decode_every,",
                "decode_every, backend",
            ],
        ),
        (["zoo", "info", "nope"], ["no model 'nope'"]),
        (
            ["evaluate", "warmstart", "--model", "hf://org/nope", "problems=1"],
            ["hf://org/nope: README.md is not in the Hugging Face cache", "HF_HUB_OFFLINE=1"],
        ),
    ],
)
def test_user_errors_are_one_line_and_create_nothing(tmp_path: Path, args: list[str], needles: list[str]) -> None:
    res = ttompc(*args, cwd=tmp_path)
    line = assert_user_error(res, *needles)
    assert line.startswith(f"ttompc {args[0]}: error: ")
    assert "--finalize" not in line  # the old wrong hint for a dataset that does not exist
    assert list(tmp_path.iterdir()) == []  # no output folder, no card, no checkpoint dir


def test_debug_shows_the_traceback(tmp_path: Path) -> None:
    for res in (
        ttompc("solve", "--scenario", "nope", "--debug", cwd=tmp_path),
        ttompc("solve", "--scenario", "nope", cwd=tmp_path, TTOMPC_DEBUG="1"),
    ):
        assert (
            res.returncode == 1
            and "Traceback" in res.stderr
            and "ScenarioNotFoundError: unknown scenario" in res.stderr
        )


def test_settings_may_follow_options(tmp_path: Path) -> None:
    """`COMMAND --flag X key=value`: key=value after an option still counts (the last word wins)."""
    res = ttompc("solve", "--seed", "3", "seed=4", "--print-config", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert '"seed": 4' in res.stdout


def _not_a_ttompc_file(kind: str, folder: Path) -> Path:
    """A file a user might pass as --model: a checkpoint cut short, a pickle of someone else's objects, noise."""
    import pickle

    import torch

    path = folder / f"{kind}.ckpt"
    if kind == "truncated":
        torch.save({"state_dict": {"model.w": torch.zeros(64, 64)}, "hyper_parameters": {"lr": 1.0}}, path)
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    elif kind == "foreign-pickle":
        path.write_bytes(pickle.dumps(textwrap.TextWrapper(width=7)))  # any class: the loader must not build it
    else:
        path.write_bytes(bytes(range(256)) * 16)
    return path


@pytest.mark.parametrize("kind", ["truncated", "foreign-pickle", "random-bytes"])
def test_a_file_that_is_not_a_ttompc_model_is_one_line_without_an_unpickling_hint(tmp_path: Path, kind: str) -> None:
    """Before: six lines of torch's text suggesting `weights_only=False`, an unsafe hint for a file from elsewhere."""
    inputs = tmp_path / "in"
    inputs.mkdir()
    bad = _not_a_ttompc_file(kind, inputs)
    res = ttompc("evaluate", "warmstart", "--model", str(bad), "problems=1", "out=out", cwd=tmp_path)
    line = assert_user_error(res, str(bad), "is not a ttompc checkpoint", "expected a Lightning .ckpt written by")
    assert "weights_only" not in res.stderr and "Re-running" not in res.stderr, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]


def test_damaged_safetensors_from_zoo_publish(tmp_path: Path) -> None:
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    (bundle / "model.safetensors").write_bytes(b"\x08\x00\x00\x00\x00\x00\x00\x00{not json")
    (bundle / "config.json").write_text("{}")
    res = ttompc(
        "zoo",
        "publish",
        str(bundle),
        "--name",
        "m",
        "--to",
        str(tmp_path / "to"),
        "--skip-eval",
        "--zoo-dir",
        str(tmp_path / "zoo"),
        cwd=tmp_path,
    )
    assert_user_error(res, "model.safetensors is damaged or not a safetensors file", "re-export")
    assert not (tmp_path / "to").exists() and not (tmp_path / "zoo").exists()


def test_zoo_list_into_a_closed_pipe_is_quiet(tmp_path: Path) -> None:
    """`ttompc zoo list | head -0`: the reader is gone before we write; no 'Broken pipe', no traceback."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "ttompc.cli", "zoo", "list"],
        cwd=tmp_path,
        env=cli_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()
    err = proc.stderr.read()
    proc.wait(timeout=60)
    assert err == "", err
    assert proc.returncode != 0  # like any program killed by SIGPIPE, but silently


def test_solve_does_not_import_lightning(tmp_path: Path) -> None:
    code = (
        "import sys; from ttompc.cli import main; rc = main(['solve', '--json']); "
        "assert 'lightning' not in sys.modules and 'torch' not in sys.modules, 'imported'; sys.exit(rc)"
    )
    res = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=cli_env(), capture_output=True, text=True)
    assert res.returncode == 0, res.stderr


def test_help_says_what_the_tool_is(tmp_path: Path) -> None:
    res = ttompc("--help", cwd=tmp_path)
    assert res.returncode == 0
    first = res.stdout.split("\n\n")[1].replace("\n", " ")
    assert first.startswith("ttompc: plan") and "transformer" in first and "``" not in res.stdout


def _terminal_sigint() -> None:
    """The child gets SIGINT's default disposition, as a program started from a terminal has: a test run that was
    itself started in the background (``cmd &`` in a script ignores SIGINT) would otherwise pass that on."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_during_generate_says_how_to_resume(tmp_path: Path) -> None:
    """Ctrl-C in a terminal signals the whole process group: the pool workers stay quiet, the parent explains.

    No race on how far the run got: the interrupt follows an event, the first shard's record (the pool is running
    and a shard is done), and however far each worker has started it stays quiet (workers are spawned with SIGINT
    blocked until they ignore it: ``ttompc.parallel``), with 2,000 problems still to do. The bounds only stop a
    hung run, whose threads' stacks (faulthandler, on SIGABRT) then make the failure message."""
    out = tmp_path / "data"
    first = out / "meta" / "shard-00000.json"
    args = ["generate", "problems=2000", "shard_size=2", "workers=2", f"out={out}", "--no-progress"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "ttompc.cli", *args],
        cwd=tmp_path,
        env=cli_env(PYTHONFAULTHANDLER="1"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=_terminal_sigint,
    )
    try:
        stop = time.monotonic() + 600  # a safety net, not a condition of the test
        while not first.exists():
            assert proc.poll() is None and time.monotonic() < stop, proc.communicate()
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGINT)
        try:
            _, err = proc.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGABRT)
            pytest.fail(f"no exit 120 s after Ctrl-C; its threads: {proc.communicate()[1][-8000:]}")
    finally:
        if proc.poll() is None:  # only when an assertion above failed: leave no process group behind
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert err.strip().splitlines() == [
        f"ttompc generate: interrupted; re-run the same command to generate only the missing shards (finished "
        f"shards in {out} are kept)"
    ], err
    assert first.exists() and not (out / "manifest.json").exists()  # kept, and the set is not taken as complete


def test_full_disk_during_generate_names_the_path_and_keeps_finished_shards(tmp_path: Path) -> None:
    """The second shard write fails with ENOSPC; the first shard stays and the re-run completes the set."""
    out = tmp_path / "data"
    args = [
        "generate",
        "problems=4",
        "shard_size=2",
        "--splits",
        "0.5,0.25,0.25",
        "workers=1",
        f"out={out}",
        "--no-progress",
    ]
    driver = textwrap.dedent(
        f"""
        import errno, sys
        from ttompc.data import shards
        write = shards.ShardWriter.write
        def full_after_one(self, rows, index, split="train"):
            if index >= 1:
                raise OSError(errno.ENOSPC, "No space left on device")  # like pyarrow: no file name
            return write(self, rows, index, split)
        shards.ShardWriter.write = full_after_one
        from ttompc.cli import main
        sys.exit(main({args!r}))
        """
    )
    res = subprocess.run(
        [sys.executable, "-c", driver], cwd=tmp_path, env=cli_env(), capture_output=True, text=True, timeout=120
    )
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr
    line = res.stderr.strip().splitlines()[-1]
    assert f"no space left on device while writing {out}." in line  # the output folder names the full disk
    assert "re-run the same command to generate only the missing shards" in line
    assert (out / "meta" / "shard-00000.json").exists() and not (out / "meta" / "shard-00001.json").exists()
    again = ttompc(*args, cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    assert (out / "manifest.json").exists()


@pytest.mark.slow
def test_ctrl_c_during_train_says_how_to_resume_and_the_rerun_resumes(tmp_path: Path) -> None:
    data = tmp_path / "data"
    made = ttompc(
        "generate",
        "problems=4",
        "shard_size=2",
        "workers=1",
        "--splits",
        "0.5,0.25,0.25",
        f"out={data}",
        "--no-progress",
        cwd=tmp_path,
    )
    assert made.returncode == 0, made.stderr
    run = tmp_path / "run"
    argv = [
        "train",
        str(REPO / "recipes/freeflyer/tiny.yaml"),
        f"data.paths=[{data}]",
        f"trainer.out_dir={run}",
        "model.n_embd=32",
        "model.n_layer=1",
        "model.n_head=2",
        "data.batch_size=4",
        "logger.kind=none",
        "trainer.checkpoint_every_n_steps=2",
        "trainer.val_check_interval=1000",
        "trainer.export_planner=false",
    ]
    proc = subprocess.Popen(
        [sys.executable, "-m", "ttompc.cli", *argv, "trainer.max_steps=10000"],
        cwd=tmp_path,
        env=cli_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=_terminal_sigint,
    )
    deadline = time.monotonic() + 240
    while not (run / "checkpoints" / "last.ckpt").exists():
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Traceback" not in err, err
    assert f"interrupted; re-run the same command to resume from the newest checkpoint (checkpoints in {run}" in err
    again = ttompc(*argv, "trainer.max_steps=4", cwd=tmp_path, timeout=300)
    assert again.returncode == 0, again.stderr
    assert "resuming from" in again.stderr and "Traceback" not in again.stderr


@pytest.mark.parametrize(
    ("argv", "key"),
    [
        (["solve"], "seed"),
        (["generate"], "seed"),
        (["train", TINY], "trainer.seed"),
        (["finetune", str(REPO / "recipes/freeflyer/finetune.yaml")], "dagger.seed"),
        (["evaluate", "warmstart"], "seed"),
        (["evaluate", "mpc"], "seed"),
        (["demo"], "eval.seed"),
    ],
)
def test_every_command_takes_key_value_settings(argv: list[str], key: str, capsys: pytest.CaptureFixture[str]) -> None:
    """One config style: `ttompc COMMAND [RECIPE] key=value --print-config` resolves through the one loader."""
    import json

    from ttompc.cli import main

    assert main([*argv, f"{key}=5", "--print-config"]) == 0
    node = json.loads(capsys.readouterr().out)
    for part in key.split("."):
        node = node[part]
    assert node == 5
    assert main([*argv, f"{key}x=5"]) == 2
    assert f"unknown setting '{key}x'" in capsys.readouterr().err


@pytest.mark.timeout(300)  # before the fix every worker failed at start and the pool replaced it, forever
@pytest.mark.parametrize(
    ("args", "missing"),
    [
        (["warmstart", "--model", "freeflyer-tto-small", "--ft-model", "rpod-ft-tto-small"], "rpod-ft-tto-small"),
        (["mpc", "--ft-model", "nope", "max_steps=2"], "nope"),
    ],
)
def test_evaluate_with_a_model_not_in_the_zoo_stops_before_any_worker(
    tmp_path: Path, args: list[str], missing: str
) -> None:
    """A withdrawn or misspelt model is one line from the parent, which loads every model before the pool starts."""
    work, cache = tmp_path / "work", str(tmp_path / "cache")
    work.mkdir()
    cached = ttompc("zoo", "download", "freeflyer-tto-small", "--no-progress", cwd=work, TTOMPC_HOME=cache)
    assert cached.returncode == 0, cached.stderr  # a first download would draw a progress bar
    res = ttompc("evaluate", *args, "problems=2", "workers=2", "out=out", cwd=work, timeout=240, TTOMPC_HOME=cache)
    assert_user_error(res, f"no model '{missing}'", "available: ")
    assert list(work.iterdir()) == []


@pytest.mark.parametrize(
    ("model", "needles"),
    [
        (  # before: the 100-problem measurement and 1,000 rollouts (~40 CPU-minutes), then the first training step
            "freeflyer-tto-v3",
            [
                "the model freeflyer-tto-v3 is a freeflyer model but the recipe is for quadrotor (data.scenario)",
                "recipes/freeflyer/",
            ],
        ),
        (  # the right model, but the recipe's data folder is not here: refused before the measurement too
            "quadrotor-tto-v3",
            ["data.paths: dataset folder data/quadrotor-v3 does not exist", "the open-loop dataset the model was"],
        ),
    ],
)
def test_finetune_checks_model_recipe_and_data_before_it_measures_or_collects(
    tmp_path: Path, model: str, needles: list[str]
) -> None:
    """`ttompc finetune recipes/quadrotor/finetune.yaml --model M`, run as a new user runs it (no data here)."""
    work, cache = tmp_path / "work", str(tmp_path / "cache")
    work.mkdir()
    res = ttompc(
        "finetune", str(REPO / "recipes/quadrotor/finetune.yaml"), "--model", model, cwd=work, TTOMPC_HOME=cache
    )
    assert_user_error(res, "ttompc finetune: error: ", *needles)
    assert not (work / "runs" / "quadrotor-ft-tto-v5" / "dagger").exists()  # no rollout shard
    assert list(work.iterdir()) == []  # no run folder, no source planner, no state file


@pytest.mark.parametrize(
    ("bundle", "needles"),
    [
        ("freeflyer-tto-small", ["ttompc evaluate warmstart --model MODEL", "ttompc zoo metrics --method TTO "]),
        ("freeflyer-ft-tto-v4", ["ttompc evaluate mpc --ft-model MODEL", "ttompc zoo metrics --method FT-TTO "]),
    ],
)
def test_zoo_publish_without_metrics_says_how_to_make_them(tmp_path: Path, bundle: str, needles: list[str]) -> None:
    """Before: "the standard evaluation is not wired into publish yet"."""
    res = ttompc(
        "zoo",
        "publish",
        str(REPO / "zoo" / "models" / bundle),
        "--name",
        "m",
        "--to",
        str(tmp_path / "to"),
        "--zoo-dir",
        str(tmp_path / "zoo"),
        cwd=tmp_path,
    )
    line = assert_user_error(res, "ttompc zoo: error: no metrics for the card of m", *needles)
    assert "--card-metrics metrics.json" in line and "--skip-eval" in line and "wired" not in line, line
    assert list(tmp_path.iterdir()) == []


@pytest.mark.timeout(300)  # before the fix: the spawn error, from every replacement worker, forever
def test_a_script_that_runs_a_pool_command_without_a_main_guard_ends_with_one_line(tmp_path: Path) -> None:
    """Each spawned worker imports the parent's script; one that calls ``ttompc.cli.main()`` unguarded would run the
    command again there. The workers stop quietly and the parent says what to do."""
    script = tmp_path / "my_generate.py"
    script.write_text(
        "import sys\n"
        "import ttompc.cli\n\n"
        "sys.exit(ttompc.cli.main(['generate', 'problems=4', 'shard_size=1', 'workers=2', 'splits.train=0.5',\n"
        "                          'splits.val=0.5', 'splits.test=0', 'out=data', '--no-progress']))\n"
    )
    res = subprocess.run(
        [sys.executable, str(script)], cwd=tmp_path, env=cli_env(), capture_output=True, text=True, timeout=240
    )
    assert_user_error(res, "ttompc generate: error: a worker process exited", 'if __name__ == "__main__":')


@pytest.fixture(scope="module")
def two_scenarios(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A tiny free-flyer and quadrotor dataset, made as a user makes them."""
    root = tmp_path_factory.mktemp("datasets")
    out = {}
    for scenario in ("freeflyer", "quadrotor"):
        out[scenario] = root / f"{scenario}-v1"
        res = ttompc(
            "generate",
            f"scenario={scenario}",
            "problems=4",
            "shard_size=2",
            "workers=1",
            "splits.train=0.5",
            "splits.val=0.5",
            "splits.test=0",
            f"out={out[scenario]}",
            "--no-progress",
            cwd=root,
            timeout=300,
        )
        assert res.returncode == 0, res.stderr
    return out


@pytest.mark.parametrize(
    ("recipe", "paths", "extra", "needles"),
    [
        (  # before: trained silently on the free-flyer data under the quadrotor recipe's name
            "quadrotor/tiny.yaml",
            ["freeflyer"],
            [],
            [
                "the recipe is for quadrotor (data.scenario) but",
                "freeflyer-v1 holds freeflyer trajectories",
                "recipes/freeflyer/",
            ],
        ),
        (  # before: ValueError: open-loop datasets mix scenarios
            "freeflyer/tiny.yaml",
            ["freeflyer", "quadrotor"],
            [],
            ["data.paths mixes scenarios:", "freeflyer-v1 holds freeflyer", "quadrotor-v1 quadrotor"],
        ),
        (  # before: ValueError from the batcher, after Lightning had started
            "freeflyer/tiny.yaml",
            ["freeflyer"],
            ["data.context_length=500"],
            ["data.context_length=500 does not fit the 100-step freeflyer trajectories", "within [1, 100]"],
        ),
    ],
)
def test_train_on_data_that_does_not_fit_the_recipe_is_one_line(
    tmp_path: Path, two_scenarios: dict[str, Path], recipe: str, paths: list[str], extra: list[str], needles: list[str]
) -> None:
    data = ",".join(str(two_scenarios[p]) for p in paths)
    smoke = ["trainer.max_steps=1", "trainer.val_check_interval=1", "trainer.limit_val_batches=1", "logger.kind=none"]
    res = ttompc(
        "train",
        str(REPO / "recipes" / recipe),
        f"data.paths=[{data}]",
        "trainer.out_dir=run",
        *smoke,
        *extra,
        cwd=tmp_path,
        timeout=300,
    )
    assert_user_error(res, "ttompc train: error: ", *needles)
    assert list(tmp_path.iterdir()) == []


def _unusable_output(tmp_path: Path, kind: str) -> Path:
    """An output path the command may not write: inside a read-only folder, or below a file."""
    if kind == "read-only folder":
        found = read_only_folder(tmp_path)
        if found is None:
            pytest.skip("no folder here refuses this process")
        folder = found
    else:
        folder = tmp_path / "a-file"
        folder.write_text("")
    return folder / "out"


@pytest.mark.parametrize("kind", ["read-only folder", "file in the way"])
@pytest.mark.parametrize(
    "command",
    [
        "generate",
        "solve --plot",
        "zoo publish",
        "demo",
        pytest.param("evaluate", marks=pytest.mark.slow),
        "train",
    ],
)
def test_an_output_the_command_may_not_write_is_one_line(
    tmp_path: Path, kind: str, command: str, request: pytest.FixtureRequest
) -> None:
    """Before: PermissionError / NotADirectoryError tracebacks, exit 1."""
    out = _unusable_output(tmp_path, kind)
    bundle = str(REPO / "zoo" / "models" / "freeflyer-tto-small")
    argv = {
        "generate": [
            "generate",
            "problems=4",
            "shard_size=2",
            "workers=1",
            "splits.train=0.5",
            "splits.val=0.5",
            "splits.test=0",
            f"out={out}",
            "--no-progress",
        ],
        "solve --plot": ["solve", "--plot", str(out / "solve.png")],
        "zoo publish": [
            "zoo",
            "publish",
            bundle,
            "--name",
            "m",
            "--to",
            str(out),
            "--skip-eval",
            "--zoo-dir",
            str(tmp_path / "zoo"),
        ],
        "demo": ["demo", "--model", bundle, "--no-mpc", f"out={out}"],  # before: refused after planning
        "evaluate": [
            "evaluate",
            "warmstart",
            "--model",
            bundle,
            "problems=1",
            "workers=1",
            "oracle_detours=0",
            f"out={out}",
        ],
    }.get(command)
    if argv is None:
        data = request.getfixturevalue("two_scenarios")["freeflyer"]
        argv = [
            "train",
            TINY,
            f"data.paths=[{data}]",
            f"trainer.out_dir={out}",
            "trainer.max_steps=1",
            "logger.kind=none",
        ]
    try:
        res = ttompc(*argv, cwd=tmp_path, timeout=300)
    finally:
        if out.parent.is_relative_to(tmp_path):
            out.parent.chmod(0o755)
    line = assert_user_error(res, f"ttompc {argv[0]}: error: cannot use {out.parent}", "choose a location you can")
    reasons = ("not a directory", "file exists", "permission denied", "operation not permitted", "read-only file")
    assert any(reason in line for reason in reasons), line
