"""``ttompc evaluate compare``: two closed-loop reports paired on the same held-out problems. The paired statistics
are a direct numpy computation over the problems both ran feasibly, goals lost and won are counted per problem, the
filters select rows, reports of different problems are refused (one line, exit status 2), and the command imports
neither torch nor Lightning."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ttompc.cli import main
from ttompc.errors import UserError
from ttompc.evaluation.compare import compare_reports, format_comparison, load_report
from ttompc.evaluation.stats import interval

COLUMNS = ["problem", "seed", "method", "horizon", "cost", "rel_cost", "mean_step_time", "terminal_error", "feasible"]
COLUMNS += ["plant", "rel_increment"]
PROBLEMS = 6


def write_report(folder: Path, runs: list[dict[str, Any]], config: dict[str, Any] | None = None) -> Path:
    """A report folder as ``ttompc evaluate mpc`` writes it: mpc_runs.csv (nan increment when infeasible), mpc.json
    (marked complete)."""
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "mpc_runs.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        for r in runs:
            inc = r["rel_increment"] if r["feasible"] else float("nan")
            w.writerow(
                {
                    "problem": r["problem"],
                    "seed": r.get("seed", 1000 + r["problem"]),
                    "method": r["method"],
                    "horizon": r["horizon"],
                    "cost": 0.2 * (1 + inc),
                    "rel_cost": 0.2,
                    "plant": r.get("plant", "nominal"),
                    "mean_step_time": r["mean_step_time"],
                    "terminal_error": 0.0,
                    "feasible": r["feasible"],
                    "rel_increment": inc,
                }
            )
    report = {"summary": [], "complete": True} | ({"config": config} if config is not None else {})
    (folder / "mpc.json").write_text(json.dumps(report))
    return folder


def runs(
    method: str, horizon: int, feasible: list[bool], seed: int, problems: range = range(PROBLEMS)
) -> list[dict[str, Any]]:
    rng = np.random.default_rng(seed)
    return [
        {
            "problem": p,
            "method": method,
            "horizon": horizon,
            "feasible": feasible[p],
            "rel_increment": float(rng.uniform(0, 0.5)),
            "mean_step_time": float(rng.uniform(0.005, 0.02)),
        }
        for p in problems
    ]


BASE_FEASIBLE = [True, True, True, False, True, True]
OTHER_FEASIBLE = [True, False, True, True, True, False]  # problems 1 and 5 lost, problem 3 won


@pytest.fixture
def reports(tmp_path: Path) -> tuple[Path, Path, list[dict[str, Any]], list[dict[str, Any]]]:
    config = {"scenario": "freeflyer", "seed": 4242, "problems": PROBLEMS, "protocol": "paper"}
    base_runs = [*runs("REL-MPC", 10, [True] * 6, 1), *runs("TTO-MPC", 10, BASE_FEASIBLE, 2)]
    base_runs += [*runs("TTO-MPC", 30, [True] * 6, 3), *runs("PLAN-ONCE", 10, [True] * 6, 4)]
    other_runs = [*runs("TTO-MPC", 10, [*OTHER_FEASIBLE, True], 5, range(PROBLEMS + 1))]  # problem 6: not in base
    other_runs += [*runs("TTO-MPC", 30, [True] * 6, 6), *runs("REL-MPC", 10, [True] * 6, 7)]  # no PLAN-ONCE
    base = write_report(tmp_path / "base", base_runs, config)
    other = write_report(tmp_path / "other", other_runs, {**config, "problems": PROBLEMS + 1, "protocol": "zoo"})
    return base, other, base_runs, other_runs


def _pick(rows: list[dict[str, Any]], method: str, horizon: int) -> dict[str, Any]:
    (row,) = [r for r in rows if r["method"] == method and r["horizon"] == horizon]
    return row


def test_paired_difference_goals_and_step_ratio_are_those_of_numpy(reports: Any) -> None:
    base, other, base_runs, other_runs = reports
    rows = compare_reports(base, [other])
    assert [(r["method"], r["horizon"]) for r in rows] == [("REL-MPC", 10), ("TTO-MPC", 10), ("TTO-MPC", 30)]
    row = _pick(rows, "TTO-MPC", 10)
    assert (row["base"], row["other"], row["plant"]) == ("base", "other", "nominal")
    assert row["problems"] == PROBLEMS  # problem 6 ran in the other report only
    assert (row["base_goals"], row["other_goals"], row["lost"], row["won"]) == (5, 4, 2, 1)

    b = {r["problem"]: r for r in base_runs if r["method"] == "TTO-MPC" and r["horizon"] == 10}
    o = {r["problem"]: r for r in other_runs if r["method"] == "TTO-MPC" and r["horizon"] == 10}
    both = [p for p in range(PROBLEMS) if BASE_FEASIBLE[p] and OTHER_FEASIBLE[p]]
    diff = np.array([100 * (o[p]["rel_increment"] - b[p]["rel_increment"]) for p in both])
    paired = row["paired"]
    assert paired["n"] == len(both) == 3
    assert paired["mean"] == pytest.approx(diff.mean(), rel=1e-9)
    assert paired["se"] == pytest.approx(diff.std(ddof=1) / np.sqrt(len(diff)), rel=1e-9)
    assert paired["lo"] <= paired["mean"] <= paired["hi"]
    assert (paired["lo"], paired["hi"]) == pytest.approx((interval(diff)["lo"], interval(diff)["hi"]), rel=1e-9)

    step = [np.mean([runs_[p]["mean_step_time"] for p in range(PROBLEMS)]) for runs_ in (b, o)]
    assert row["step_ratio"] == pytest.approx(step[0] / step[1], rel=1e-9)
    assert row["base_step_time"] == pytest.approx(step[0], rel=1e-9)


def test_table_labels_reports_by_folder_and_shows_counts(reports: Any) -> None:
    base, other, *_ = reports
    rows = compare_reports(base, [other / "mpc_runs.csv"])  # the CSV path works as the folder does
    table = format_comparison(rows)
    assert "### other against base" in table
    assert "| nominal | TTO-MPC | 10 | 5 → 4 / 6 | 2 / 1 |" in table
    assert f"({_pick(rows, 'TTO-MPC', 10)['paired']['n']}) | {_pick(rows, 'TTO-MPC', 10)['step_ratio']:.2f}× |" in table
    assert max(len(line) for line in table.splitlines()) <= 120


def test_same_folder_names_are_labelled_by_path(reports: Any, tmp_path: Path) -> None:
    base, other, _, other_runs = reports
    twin = write_report(tmp_path / "elsewhere" / "other", other_runs)
    rows = compare_reports(base, [other, twin])
    assert list(dict.fromkeys(r["other"] for r in rows)) == [str(other), str(twin)]
    assert len(rows) == 6


def test_filters_select_methods_and_horizons(reports: Any) -> None:
    base, other, *_ = reports
    assert {r["method"] for r in compare_reports(base, [other], methods=["TTO-MPC"])} == {"TTO-MPC"}
    assert {r["horizon"] for r in compare_reports(base, [other], horizons=[30])} == {30}
    rows = compare_reports(base, [other], methods=["REL-MPC", "TTO-MPC"], horizons=[10])
    assert [(r["method"], r["horizon"]) for r in rows] == [("REL-MPC", 10), ("TTO-MPC", 10)]
    with pytest.raises(UserError, match=r"share no \(plant, method, horizon\) among methods PLAN-ONCE"):
        compare_reports(base, [other], methods=["PLAN-ONCE"])  # the other report did not run it


def test_reports_of_different_problems_are_refused(reports: Any, tmp_path: Path) -> None:
    base, _, _, other_runs = reports
    moved = [{**r, "seed": 7} if r["problem"] == 2 and r["method"] == "TTO-MPC" else r for r in other_runs]
    with pytest.raises(UserError, match="problem 2 of TTO-MPC at H = 10 on the nominal plant has seed 1002 in base"):
        compare_reports(base, [write_report(tmp_path / "moved", moved)])
    config = {"scenario": "freeflyer", "seed": 7, "problems": PROBLEMS}
    with pytest.raises(UserError, match="different problems \\(seed 4242 vs 7"):
        compare_reports(base, [write_report(tmp_path / "seed7", other_runs, config)])
    with pytest.raises(UserError, match="no closed-loop report at"):
        compare_reports(base, [tmp_path / "missing"])
    assert load_report(base).config == {"scenario": "freeflyer", "seed": 4242, "problems": 6, "protocol": "paper"}


def test_cli_prints_the_table_and_writes_json(reports: Any, tmp_path: Path) -> None:
    base, other, *_ = reports
    out = tmp_path / "cmp" / "rows.json"
    code = (
        "import sys; from ttompc.cli import main; "
        f"rc = main(['evaluate', 'compare', {str(base)!r}, {str(other)!r}, '--methods', 'TTO-MPC', '--horizons', "
        f"'10,30', '--json', {str(out)!r}]); "
        "assert 'lightning' not in sys.modules and 'torch' not in sys.modules, 'imported'; sys.exit(rc)"
    )
    res = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "| nominal | TTO-MPC | 10 | 5 → 4 / 6 | 2 / 1 |" in res.stdout and "REL-MPC" not in res.stdout
    rows = json.loads(out.read_text())
    assert [(r["method"], r["horizon"]) for r in rows] == [("TTO-MPC", 10), ("TTO-MPC", 30)]
    assert rows[0]["paired"]["mean"] == pytest.approx(compare_reports(base, [other])[1]["paired"]["mean"])


def test_cli_mismatch_is_one_line_and_exit_2(reports: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    base, _, _, other_runs = reports
    moved = write_report(tmp_path / "moved", [{**r, "seed": 1} for r in other_runs])
    assert main(["evaluate", "compare", str(base), str(moved)]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ttompc evaluate: error: problem 0 of "), captured.err
    assert "same scenario and seed" in lines[0] and captured.out == ""
    assert main(["evaluate", "compare", str(base), str(moved), "--horizons", "ten"]) == 2
    assert "--horizons ten is not a list of integers" in capsys.readouterr().err


def test_the_report_and_compare_pair_alike(
    reports: tuple[Path, Path, list[dict[str, Any]], list[dict[str, Any]]],
) -> None:
    """One paired comparison (``stats.paired``): a method against REL-MPC within a report (its vs_rel_mpc column)
    is what ``evaluate compare`` gives for the two as separate reports, up to the points' scale; problems only one
    side ran are left out."""
    from ttompc.evaluation.closed_loop_report import summarize
    from ttompc.evaluation.stats import Outcome, paired

    _, _, base_runs, _ = reports
    recs = [
        {
            **r,
            "plant": "nominal",
            "cost": 1.0,
            "rel_cost": 1.0,
            "max_step_time": 0.1,
            "fallbacks": 0,
            "target_change": 0.1,
            "terminal_error": 0.0,
            "mean_iterations": 1.0,
            "mean_iterations_solved": 1.0,
            "complete": True,
            "rel_increment": r["rel_increment"] if r["feasible"] else float("nan"),
        }
        for r in base_runs
        if r["horizon"] == 10 and r["method"] != "PLAN-ONCE"
    ]
    (row,) = [r for r in summarize(recs) if r["method"] == "TTO-MPC"]
    rel = {r["problem"]: Outcome.of(r) for r in recs if r["method"] == "REL-MPC"}
    tto = {r["problem"]: Outcome.of(r) for r in recs if r["method"] == "TTO-MPC"}
    pair = paired(rel, tto, scale=100)
    assert row["vs_rel_mpc"]["n"] == pair["paired"]["n"] == sum(BASE_FEASIBLE)
    assert 100 * row["vs_rel_mpc"]["mean"] == pytest.approx(pair["paired"]["mean"], rel=1e-12)
    assert (pair["problems"], pair["base_goals"], pair["other_goals"], pair["lost"], pair["won"]) == (6, 6, 5, 1, 0)
    assert paired({**rel, 99: rel[0]}, tto)["problems"] == 6 and paired(rel, {})["paired"]["n"] == 0


@pytest.mark.parametrize("damage", ["no mpc.json", "not complete"])
def test_an_incomplete_report_is_never_paired(
    reports: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str], damage: str
) -> None:
    """A folder whose run stopped before its mpc.json was written, or whose mpc.json is not marked complete (an
    older ttompc), is refused in one line, whether named by its folder or its mpc_runs.csv."""
    base, other, _, _ = reports
    if damage == "no mpc.json":
        (other / "mpc.json").unlink()
    else:
        (other / "mpc.json").write_text(json.dumps({"config": {"scenario": "freeflyer", "seed": 4242}}))
    for given in (other, other / "mpc_runs.csv"):
        with pytest.raises(UserError, match=r"mpc\.json"):
            compare_reports(base, [given])
    assert main(["evaluate", "compare", str(base), str(other)]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("ttompc evaluate: error: ") and "run `ttompc evaluate mpc" in line
