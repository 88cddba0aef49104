"""Scenarios from outside the package (docs/scenarios.md): the spec forms (file, module, entry point), their one-line
errors, pool workers that load the parent's scenario by spec, and ``ttompc check-scenario`` on the worked example
and on scenarios with a planted mistake. The end-to-end run of the example is tests/test_example_scenario.py."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest
from scenario_plants import EXAMPLE

from ttompc.cli import main as cli_main
from ttompc.parallel import pool_map
from ttompc.scenarios import (
    ENTRY_POINT_GROUP,
    ScenarioNotFoundError,
    find_scenario,
    get_scenario,
    list_scenarios,
    scenario_spec,
)

PLANTS = Path(__file__).with_name("scenario_plants.py")
SCENARIO_SOURCE = """
    import numpy as np
    from examples_di2d import DoubleIntegrator2D

    class {cls}(DoubleIntegrator2D):
        name = "{name}"
"""


def _module(root: Path, module: str, cls: str, name: str) -> None:
    """A module ``module`` on ``root`` defining ``cls`` (named ``name``), a subclass of the worked example."""
    (root / "examples_di2d.py").write_text(Path(EXAMPLE.rpartition(":")[0]).read_text())
    (root / f"{module}.py").write_text(textwrap.dedent(SCENARIO_SOURCE.format(cls=cls, name=name)))


def test_file_spec_loads_registers_and_records_an_absolute_path(monkeypatch: pytest.MonkeyPatch) -> None:
    example = Path(EXAMPLE.rpartition(":")[0])
    monkeypatch.chdir(example.parents[1])
    sc = get_scenario("examples/di2d.py:DoubleIntegrator2D")
    assert sc.name == "di2d" and (sc.state_dim, sc.control_dim, sc.n_steps) == (4, 2, 40)
    assert get_scenario("di2d") is sc and get_scenario(EXAMPLE) is sc  # one class, one instance per process
    assert scenario_spec(sc) == EXAMPLE and find_scenario("di2d", "no/such/file.py:X") is sc
    assert "di2d" in list_scenarios()


def test_module_spec_and_entry_point(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``module:Class`` on sys.path, and an installed package's entry point (a dist-info folder on sys.path is what
    pip leaves behind)."""
    _module(tmp_path, "mymod_scenarios", "ModScenario", "mod-scenario")
    _module(tmp_path, "eppkg_scenarios", "EpScenario", "ep-scenario")
    dist = tmp_path / "eppkg-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: eppkg\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text(f"[{ENTRY_POINT_GROUP}]\nep-scenario = eppkg_scenarios:EpScenario\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert get_scenario("mymod_scenarios:ModScenario").name == "mod-scenario"
    assert scenario_spec("mod-scenario") == "mymod_scenarios:ModScenario"
    assert "ep-scenario" in list_scenarios()
    sc = get_scenario("ep-scenario")
    assert type(sc).__name__ == "EpScenario" and scenario_spec(sc) == "ep-scenario"


@pytest.mark.parametrize(
    ("spec", "needle"),
    [
        ("nope", "unknown scenario 'nope'; choose one of: "),
        ("no_such_module_xyz:Thing", "no module named 'no_such_module_xyz'"),
        ("missing/di2d.py:DoubleIntegrator2D", "scenario file"),
        (EXAMPLE.replace(":DoubleIntegrator2D", ":Nope"), "has no attribute 'Nope'; it defines: DoubleIntegrator2D"),
        (EXAMPLE.replace(":DoubleIntegrator2D", ":CENTRE"), "not a Scenario subclass"),
        ("ttompc.scenarios.base:Scenario", "does not implement batched_model"),
    ],
)
def test_specs_that_name_no_scenario_are_one_line_errors(spec: str, needle: str) -> None:
    with pytest.raises(ScenarioNotFoundError) as info:
        get_scenario(spec)
    assert needle in str(info.value) and "\n" not in str(info.value)


def test_a_builtin_name_is_not_taken_over(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _module(tmp_path, "taker_scenarios", "Taker", "quadrotor")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ScenarioNotFoundError, match=r"'quadrotor' is already taken by ttompc\.scenarios\.quadrotor"):
        get_scenario("taker_scenarios:Taker")


def test_cli_errors_for_a_bad_spec_are_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["solve", "scenario=missing/di2d.py:DoubleIntegrator2D"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("ttompc solve: error: missing/di2d.py:DoubleIntegrator2D: scenario file")


def _loaded_name(_: int) -> str:
    return get_scenario("di2d").name  # resolves only if the worker loaded the parent's spec first


def test_spawned_workers_load_the_scenario_by_spec() -> None:
    spec = scenario_spec(get_scenario(EXAMPLE))
    assert list(pool_map(_loaded_name, [0, 1], 2, scenarios=[spec], pin_torch=False)) == ["di2d", "di2d"]


def test_example_plot_draws_its_keepout_disc() -> None:
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sc = get_scenario(EXAMPLE)
    problem = sc.sample(np.random.default_rng(0))
    fig, ax = plt.subplots()
    sc.plot(ax, problem, {"guess": sc.initial_guess(problem)[0]})
    assert len(ax.patches) == 1 and ax.patches[0].get_radius() == 1.0
    plt.close(fig)


def test_check_scenario_passes_the_example(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["check-scenario", EXAMPLE, "problems=2"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[-1] == "all checks passed" and sum(line.startswith("ok") for line in out) == 10
    assert any(line.startswith("ok    fused_step: the fused decoder's compiled step matches") for line in out)


def test_check_scenario_rejects_a_trust_norm_the_engine_does_not_have(capsys: pytest.CaptureFixture[str]) -> None:
    """The trust-region norm is the scenario's setting (``Scenario.trust_norm``): a wrong one stops at the interface."""
    assert cli_main(["check-scenario", f"{PLANTS}:WrongTrustNorm", "problems=1"]) == 1
    out = capsys.readouterr().out.splitlines()
    assert "FAIL  interface: trust_norm must be 'l2' or 'linf', got 'l1'" in out and out[-1].endswith("interface")


@pytest.mark.parametrize(
    ("plant", "failed", "needle", "ran"),
    [
        # the wrong slope also breaks REL (one convex solve on a wrong model): the first failure names the cause
        (
            "WrongJacobian",
            ["jacobian", "solve"],
            "A[0, 2] at step 0 is 0.5 but finite differences of step() give 0.25",
            10,
        ),
        ("WrongBatchedModel", ["batched_model"], "but the scenario's step gives", 10),
        # the one source differs from a hand-written step(): every form derived from it is named
        (
            "WrongCompiledStep",
            ["convex_model", "jacobian", "batched_model", "fused_step", "solve"],
            "A x + B u + c differs from step() at the reference it was built on",
            10,
        ),
        ("UnsolvableSampler", ["solve"], "REL infeasible after 1 iteration(s)", 10),
        # a broken interface stops the checks: the others would fail for the same reason
        ("NegativePerturbation", ["interface"], "perturbation must be (gain_std, actuation_std, process_std)", 1),
        ("NoDynamics", ["interface"], "a CompiledScenario declares dynamics = CompiledStep", 1),
    ],
)
def test_check_scenario_names_a_planted_mistake_in_one_line(
    plant: str, failed: list[str], needle: str, ran: int, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli_main(["check-scenario", f"{PLANTS}:{plant}", "problems=1"]) == 1
    out = capsys.readouterr().out.splitlines()
    lines = [line for line in out if line.startswith("FAIL")]
    assert [line.split()[1].rstrip(":") for line in lines] == failed, out
    assert needle in lines[0], lines[0]
    assert out[-1] == f"{len(failed)} of {ran} checks failed: {', '.join(failed)}"
