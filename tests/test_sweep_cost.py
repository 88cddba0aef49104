"""The cost of a closed-loop sweep (``ttompc.evaluation.sweep_cost``): measured per method, horizon and plant; the
CPU-hours of a grid added up from it; the grid a budget buys; and the command lines ``make figures`` runs."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import mpc_fakes
import pytest

from ttompc.evaluation import sweep_cost
from ttompc.evaluation.closed_loop import ClosedLoopConfig
from ttompc.evaluation.machine import cpu_model
from ttompc.mpc.methods import methods_for

ROOT = Path(__file__).resolve().parents[1]


def _entry(cpu: str = "a test CPU") -> dict[str, Any]:
    """Two methods: A costs 1 s at H = 10 and 3 s at H = 30 (nominal), 2 and 4 s perturbed; B 0.5 s at every H,
    nominal only; building a problem 2 s."""
    episodes = {
        "A": {"nominal": {"10": 1.0, "30": 3.0}, "perturbed": {"10": 2.0, "30": 4.0}},
        "B": {"nominal": {"10": 0.5}},
    }
    machine = {"cpu": cpu, "cpus": 2, "load_average": [1.0, 1.0, 1.0], "load_average_end": [1.0, 1.0, 1.5]}
    return {"problem_s": 2.0, "episode_s": episodes, "machine": machine}


def test_an_episode_costs_the_measured_seconds_interpolated_in_the_horizon() -> None:
    e = _entry()
    assert sweep_cost.episode_seconds(e, "A", "nominal", 10) == 1.0
    assert sweep_cost.episode_seconds(e, "A", "nominal", 20) == pytest.approx(2.0)  # between 10 and 30
    assert sweep_cost.episode_seconds(e, "A", "nominal", 100) == pytest.approx(10.0)  # the last two extrapolated
    assert sweep_cost.episode_seconds(e, "A", "perturbed", 20) == pytest.approx(3.0)
    assert sweep_cost.episode_seconds(e, "B", "perturbed", 50) == 0.5  # not measured there: nominal's, one H


def test_a_sweep_costs_its_problems_times_every_episode_of_one() -> None:
    # per problem: 2 s to build; A at H = 10 and 30 on both plants 1 + 3 + 2 + 4; B 4 x 0.5
    assert sweep_cost.sweep_hours(_entry(), 360, [10, 30], ["nominal", "perturbed"]) == pytest.approx(
        360 * (2 + 10 + 2) / 3600
    )
    assert sweep_cost.sweep_hours(_entry(), 3600, [10], ["nominal"]) == pytest.approx(2 + 1 + 0.5)


def test_a_budget_buys_the_paper_grid_at_the_minimum_problems_else_the_reduced_one() -> None:
    e, plants = _entry(), ["nominal"]
    per = {name: sweep_cost.sweep_hours(e, 1, grid, plants) for name, grid in sweep_cost.GRIDS.items()}
    assert per["minimal"] < per["reduced"] < per["paper"]
    rich = sweep_cost.plan(e, 1000 * per["paper"], plants)
    assert (rich["grid"], rich["problems"]) == ("paper", sweep_cost.MAX_PROBLEMS)
    between = sweep_cost.plan(e, 150 * per["reduced"], plants)  # reduced at 150 problems, the paper grid short of 100
    assert between["grid"] == "reduced" and between["problems"] in (149, 150)
    assert between["hours"] <= 150 * per["reduced"] + 1e-9
    poor = sweep_cost.plan(e, 10 * per["reduced"], plants)  # not 100 on any grid: the reduced grid, fewer problems
    assert poor["grid"] == "reduced" and poor["problems"] in (9, 10)
    assert 100 * per["minimal"] < 50 * per["reduced"]  # the minimal grid affords 100, the reduced one 50: reduced
    assert sweep_cost.plan(e, 50 * per["reduced"], plants)["grid"] == "reduced"
    tiny = sweep_cost.plan(e, 1.5 * per["reduced"], plants)  # not two problems on the reduced grid: the minimal one
    assert tiny["grid"] == "minimal" and tiny["problems"] == 5  # 1.5 x 25.5 s buys 5 of 7 s
    assert sweep_cost.plan(e, 0.0, plants)["problems"] == 0


def test_the_makefile_runs_the_grids_the_planner_prices() -> None:
    text = (ROOT / "Makefile").read_text()
    grids = dict(re.findall(r"^FIG_HORIZONS_(\w+) := (\[[\d,]+\])$", text, re.MULTILINE))
    assert {name: json.loads(grid) for name, grid in grids.items()} == sweep_cost.GRIDS


def test_estimate_and_plan_print_cpu_hours(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    costs = tmp_path / "cost.json"
    costs.write_text(json.dumps({"freeflyer": _entry(cpu_model())}))
    args = ["--costs", str(costs), "estimate", "--scenario", "freeflyer", "--problems", "360", "--horizons", "[10,30]"]
    assert sweep_cost.main(args) == 0
    assert "about 1.4 CPU-hours on this machine (0.7 h on 2 idle cores" in capsys.readouterr().out
    assert sweep_cost.main(["--costs", str(costs), "plan", "--budget", "5", "--plants", "[nominal]"]) == 0
    printed = capsys.readouterr().out
    assert "| freeflyer |" in printed and "FIG_GRID=" in printed


@pytest.mark.parametrize(
    ("content", "scenario", "message"),
    [
        (None, "freeflyer", "no sweep costs at"),
        ("not json", "freeflyer", "is not a sweep-cost file"),
        (json.dumps({"freeflyer": _entry()}), "rpod", "holds no costs of rpod (it has freeflyer)"),
    ],
)
def test_missing_costs_are_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: str | None, scenario: str, message: str
) -> None:
    costs = tmp_path / "cost.json"
    if content is not None:
        costs.write_text(content)
    args = ["--costs", str(costs), "estimate", "--scenario", scenario, "--problems", "2", "--horizons", "10"]
    assert sweep_cost.main(args) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


def test_measure_times_every_method_at_every_horizon_and_plant() -> None:
    """Baselines only, on the short scenario, three steps an episode: every method has a cost at each H and plant."""
    cfg = ClosedLoopConfig(
        scenario=mpc_fakes.FreeFlyerShort.name,
        problems=1,
        horizons=[5, 10],
        max_steps=3,
        robust_blend=0.0,
        plants=["nominal", "perturbed"],
    )
    entry = sweep_cost.measure(cfg)
    assert set(entry["episode_s"]) == {m.name for m in methods_for({}, 0.0)}
    for by_plant in entry["episode_s"].values():
        assert set(by_plant) == {"nominal", "perturbed"}
        assert all(set(cells) == {"5", "10"} and min(cells.values()) >= 0 for cells in by_plant.values())
    assert entry["problem_s"] >= 0 and entry["machine"]["cpu"] == cpu_model()


def test_a_second_measurement_adds_its_horizons_to_the_same_settings_only() -> None:
    same = {"problems": 2, "seed": 4242, "protocol": "recommended", "models": {"TTO": "m"}}
    first = {**_entry(), **same, "commands": ["first"]}
    second = {**same, "problem_s": 3.0, "episode_s": {"A": {"nominal": {"50": 6.0, "10": 1.5}}}, "commands": ["2nd"]}
    merged = sweep_cost.merge(first, {**_entry(), **second})
    assert merged["episode_s"]["A"] == {
        "nominal": {"10": 1.5, "30": 3.0, "50": 6.0},
        "perturbed": {"10": 2.0, "30": 4.0},
    }
    assert merged["episode_s"]["B"] == {"nominal": {"10": 0.5}} and merged["problem_s"] == 2.0
    assert merged["commands"] == ["first", "2nd"]
    other = {**_entry(), **second, "protocol": "paper"}
    assert sweep_cost.merge(first, other) == other  # measured under another protocol: it replaces the first
