"""Bad input, as a user types it: every case runs through the real CLI (``ttompc.cli.main`` in a subprocess,
``tests/cli_batch.py``, many cases per interpreter) and must end in exit code 2 with one line on stderr naming the
problem, no traceback, and no file created, changed or removed.

Two tables: the cases of issue 58 (each once a traceback, a silent acceptance or a wrong report), and cases generated
from the command schemas (every numeric setting at 0, -1 and a huge value, every list empty and, where its items
are numbers, of one huge item, every path missing, a file, a read-only folder), whose verdicts must match the ranges
the schemas declare (``ttompc.ranges``). The generated settings cases go through ``--print-config``, which exits
before any work once the settings load; what depends on the machine or the scenario (processes beyond the cores, a
horizon beyond N) is listed, run as far as the command's checks. The Python entries (``train``, ``finetune``,
``generate``, the evaluations' runners, ``Planner.from_pretrained``, ``solve_problem``, ``get_scenario``;
``bad_input_api``) refuse the same inputs with the project's typed errors, in the words of the CLI's line.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any

import pytest
from bad_input_api import API_CALLS
from bad_input_cases import (
    BUNDLE,
    ENV,
    LISTED,
    NEEDS_NO_GPU,
    REPO,
    SCHEMAS,
    TINY,
    generated_cases,
    make_world,
    path_cases,
    settings_of,
)
from cli_batch import snapshot as cli_snapshot

from ttompc.evaluation.warmstart import WarmStartConfig
from ttompc.ranges import Allowed


def _cuda() -> bool:
    import torch

    return bool(torch.cuda.is_available())


def test_every_numeric_and_list_setting_declares_its_range() -> None:
    """The schemas state what each number and list may be (``ttompc.ranges.setting``), so none is left unchecked."""
    undeclared = [
        f"{cmd}: {key}"
        for cmd, (schema, _) in SCHEMAS.items()
        for key, _, allowed in settings_of(schema)
        if allowed is None
    ]
    assert undeclared == []


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """The folders the cases point at (``bad_input_cases.make_world``)."""
    return make_world(tmp_path_factory.mktemp("world"))


def _fill(text: str, world: dict[str, str]) -> str:
    return text.format(**world) if "{" in text else text


@pytest.fixture(scope="module")
def results(world: dict[str, str], tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, Any]]:
    """Every case of the three tables, run in one subprocess in the world's folder."""
    cases = [
        {
            "id": i,
            "argv": [_fill(a, world) for a in argv],
            "env": {k: _fill(v, world) for k, v in ENV.get(i, {}).items()},
        }
        for i, argv, _ in [*LISTED, *path_cases()]
    ]
    cases += [{"id": i, "argv": argv, "env": {}} for i, argv, *_ in generated_cases()]
    spool = tmp_path_factory.mktemp("spool")
    (spool / "cases.json").write_text(json.dumps(cases))
    env = {k: v for k, v in os.environ.items() if k != "TTOMPC_DEBUG"}
    env.update(WANDB_MODE="offline", HF_HUB_OFFLINE="1", TTOMPC_PROGRESS="0", OMP_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    done = subprocess.run(
        [sys.executable, str(REPO / "tests" / "cli_batch.py"), str(spool / "cases.json"), str(spool / "out.json")],
        cwd=world["root"],
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return dict(json.loads((spool / "out.json").read_text()))


def assert_one_line(result: dict[str, Any], *needles: str) -> str:
    """Exit 2, exactly one line on stderr, no traceback, nothing in the folder created, changed or removed."""
    assert result["traceback"] is None, result["traceback"]
    lines = result["stderr"].strip().splitlines()
    assert result["code"] == 2 and len(lines) == 1, (result["code"], result["stderr"])
    assert "Traceback" not in result["stderr"]
    for needle in needles:
        assert needle in lines[0], lines[0]
    assert result["changed"] == [], result["changed"]
    return lines[0]


@pytest.mark.parametrize(("case", "argv", "needles"), LISTED, ids=[c[0] for c in LISTED])
def test_the_issues_cases_are_one_line(
    case: str, argv: list[str], needles: list[str], world: dict[str, str], results: dict[str, dict[str, Any]]
) -> None:
    if case in NEEDS_NO_GPU and _cuda():
        pytest.skip("this machine has the GPU the case asks for")
    line = assert_one_line(results[case], *(_fill(n, world) for n in needles))
    assert line.startswith(f"ttompc {argv[0]}: error: ")


PATHS = path_cases()


@pytest.mark.parametrize(("case", "argv", "needles"), PATHS, ids=[c[0] for c in PATHS])
def test_paths_that_are_missing_a_file_or_read_only_are_one_line(
    case: str, argv: list[str], needles: list[str], world: dict[str, str], results: dict[str, dict[str, Any]]
) -> None:
    if "read-only" in case and world["has_read_only"] != "True":
        # on Linux, root included, the kernel's file systems refuse everyone (``cli_batch.read_only_folder``)
        assert sys.platform != "linux", "no folder refuses this process"
        pytest.skip("no folder here refuses this process")
    assert_one_line(results[case], *(_fill(n, world) for n in needles))


GENERATED = generated_cases()


@pytest.mark.parametrize(("case", "argv", "key", "value", "allowed"), GENERATED, ids=[c[0] for c in GENERATED])
def test_each_setting_at_its_edges_is_taken_or_refused_as_its_schema_declares(
    case: str, argv: list[str], key: str, value: Any, allowed: Allowed | None, results: dict[str, dict[str, Any]]
) -> None:
    """A value its declared range refuses is one line naming the key and the value; one it admits loads (or a check
    across settings refuses it in one line naming the key), never a traceback."""
    result = results[case]
    leaf = key.rsplit(".", 1)[-1]
    assert allowed is not None  # test_every_numeric_and_list_setting_declares_its_range
    if not allowed.admits(value):
        assert_one_line(result, f"{leaf}={json.dumps(value)}", "must be")
    elif result["code"] != 0:
        assert_one_line(result, leaf)
    else:
        assert result["traceback"] is None and result["changed"] == []


@pytest.mark.parametrize("case", API_CALLS)
def test_the_python_entries_refuse_in_the_clis_words(
    case: str, world: dict[str, str], results: dict[str, dict[str, Any]], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The library call behind a command refuses what the command refuses, before any work, with a ``UserError``
    (the project's typed errors derive from it) whose text is the CLI's line after ``ttompc CMD: error:``."""
    from ttompc.errors import UserError

    monkeypatch.chdir(world["root"])
    before = cli_snapshot(Path(world["root"]))
    with pytest.raises(UserError) as raised:
        API_CALLS[case](world)
    argv = next(argv for i, argv, _ in [*LISTED, *PATHS] if i == case)
    assert f"ttompc {argv[0]}: error: {raised.value}" == results[case]["stderr"].strip()
    assert cli_snapshot(Path(world["root"])) == before


def test_public_calls_refuse_what_they_cannot_use_with_typed_errors() -> None:
    """``get_scenario(None)``, a problem that is not one, a warm start of another shape: typed, one line."""
    import numpy as np

    import ttompc
    from ttompc.errors import InputError
    from ttompc.scenarios import ScenarioNotFoundError
    from ttompc.solvers.scp import SCPProblem, solve_scp

    with pytest.raises(ScenarioNotFoundError, match=r"unknown scenario None; choose one of: (.*, )?freeflyer"):
        ttompc.get_scenario(None)  # type: ignore[arg-type]
    ff = ttompc.get_scenario("freeflyer")
    problem = ff.sample(np.random.default_rng(0))
    with pytest.raises(InputError, match="not a freeflyer problem: None"):
        ttompc.solve_problem(ff, None)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="not a scenario: 'freeflyer'"):
        ttompc.solve_problem("freeflyer", problem)  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"warm start must have shapes \(101, 6\) and \(100, 3\)"):
        solve_scp(SCPProblem(ff, problem), np.zeros((3, 6)), np.zeros((2, 3)))


@pytest.mark.parametrize(("mine", "theirs"), [("quadrotor", "rpod"), ("rpod", "quadrotor"), ("quadrotor", "freeflyer")])
def test_a_problem_of_another_scenario_of_the_same_shape_is_refused(mine: str, theirs: str) -> None:
    """Free-flyer, quadrotor and RPOD problems all have 6-dim states and 100 steps; another scenario's is told apart
    by its params keys (RPOD's orbit, horizon and port: ``Scenario.problem_params``) or fixed dt (``problem_dt``)
    and refused by the solve in one line, while its own scenario takes it."""
    import numpy as np

    import ttompc
    from ttompc.errors import InputError
    from ttompc.mpc.controller import sample_problem
    from ttompc.solvers.problem import check_problem

    problem = sample_problem(ttompc.get_scenario(theirs), np.random.default_rng(0))
    check_problem(ttompc.get_scenario(theirs), problem)
    with pytest.raises(InputError, match=rf"^{mine}: its problems have .* \(another scenario's problem\?\)$") as err:
        ttompc.solve_problem(ttompc.get_scenario(mine), problem)
    assert "\n" not in str(err.value)


def test_a_run_of_a_given_datamodule_claims_its_folder_by_scenario(tmp_path: Path) -> None:
    """``train`` with a DataModule (no manifests) records the scenario and architecture, no data fingerprint, and
    refuses checkpoints of another scenario there; the same run resumes."""
    from ttompc.errors import ConfigError
    from ttompc.training.config import load_train_config
    from ttompc.training.preflight import RUN_FILE, claim_run

    cfg = load_train_config(TINY, [f"trainer.out_dir={tmp_path}"])
    dims = {"name": "freeflyer", "state_dim": 6, "control_dim": 3}
    claim_run(cfg, [], dims)
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "last.ckpt").write_bytes(b"")
    recorded = json.loads((tmp_path / RUN_FILE).read_text())
    assert recorded["scenario"] == "freeflyer" and "data" not in recorded
    claim_run(cfg, [], dims)  # the same run: resumed
    with pytest.raises(ConfigError, match="scenario freeflyer there, quadrotor here"):
        claim_run(cfg, [], {"name": "quadrotor", "state_dim": 6, "control_dim": 3})


def test_outputs_of_the_same_kind_and_configuration_are_refreshed(tmp_path: Path) -> None:
    """A warm-start report of the same configuration (but where it went and its processes), or an unfinished one,
    is replaced; a folder of published bundle files is published into again."""
    from ttompc.evaluation.report_files import check_replaceable
    from ttompc.zoo.publish import claim_destination

    config = {**asdict(WarmStartConfig(model=BUNDLE, scenario="freeflyer", problems=2)), "workers": 1}
    report = tmp_path / "warmstart.json"
    report.write_text(json.dumps({"config": {**config, "out": "elsewhere", "workers": 8}, "complete": True}))
    check_replaceable(report, "warmstart", {**config, "out": str(tmp_path)})
    report.write_text(json.dumps({"config": {**config, "problems": 5}}))  # not complete: an interrupted run's
    check_replaceable(report, "warmstart", config)
    bundle = tmp_path / "published"
    bundle.mkdir()
    for name in ("model.safetensors", "config.json", "metrics.json", ".model.safetensors.tmp"):
        (bundle / name).write_bytes(b"")
    assert claim_destination(str(bundle)) == bundle
