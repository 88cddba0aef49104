"""The closed-loop sweep: episodes stored as they finish, an interrupted sweep resumed without redoing any of them
and giving the report an uninterrupted one gives, another configuration never mixed in; and the speedup at equal
cost read off a sweep."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import mpc_fakes
import pytest

from ttompc.errors import UserError
from ttompc.evaluation import closed_loop, plots
from ttompc.evaluation.closed_loop import ClosedLoopConfig, run_closed_loop
from ttompc.evaluation.episode_store import EPISODES_FILE, EpisodeStore
from ttompc.evaluation.equal_cost import equal_cost, format_equal_cost
from ttompc.evaluation.measurement import Measurement
from ttompc.mpc.methods import methods_for
from ttompc.scenarios import get_scenario

SHORT = mpc_fakes.FreeFlyerShort.name


class Stop(Exception):
    """The interruption: raised by the fake episode runner after a number of tasks."""


def _episode(problem: int, plant: str, horizon: int, method: str) -> dict[str, Any]:
    """A deterministic stand-in for an episode's record (every field the report reads)."""
    cost = 1.0 + 0.1 * problem + 0.001 * horizon + 0.01 * len(method) + (0.05 if plant == "perturbed" else 0.0)
    feasible = (problem + horizon // 10 + len(method)) % 4 != 0
    return {
        "problem": problem,
        "seed": 100 + problem,
        "ctg0": 1,
        "method": method,
        "horizon": horizon,
        "plant": plant,
        "cost": cost,
        "rel_cost": 1.0,
        "steps": 3,
        "feasible": feasible,
        "rel_increment": cost - 1.0 if feasible else float("nan"),
        "target_change": 0.01 * problem,
        "mean_step_time": 0.001 * (1 + problem),
        "max_step_time": 0.002 * (1 + problem),
        "mean_iterations": 2.0,
        "mean_iterations_solved": 2.0,
        "fallbacks": 0,
        "terminal_error": 0.0 if feasible else 0.3,
        "complete": True,
    }


@pytest.fixture
def fake_episodes(monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """``run_problems`` replaced by ``_episode`` records (no solver), problems by stand-ins, no plots; ``calls``
    lists each task run as (problems, plant, horizon); after ``stop_after`` tasks (None: never) the next one raises
    ``Stop``."""
    state: dict[str, Any] = {"calls": [], "stop_after": None}
    names = [m.name for m in methods_for({}, 0.0)]

    def run_problems(sc: Any, eps: Any, models: Any, cfg: Any, tick: Any = None, *, runs: Any, plans: Any) -> Any:
        [(plant, run)] = runs
        if state["stop_after"] is not None and len(state["calls"]) >= state["stop_after"]:
            raise Stop
        state["calls"].append((tuple(ep.index for ep in eps), plant, run.horizon))
        return [_episode(ep.index, plant, run.horizon, m) for ep in eps for m in names]

    def problem_set(self: Measurement, scenario: Any, indices: Any = None, *, progress: str = "") -> Any:
        return [SimpleNamespace(index=i, problem=None) for i in indices]

    monkeypatch.setattr(closed_loop, "run_problems", run_problems)
    monkeypatch.setattr(closed_loop, "full_horizon_plan", lambda *args: None)
    monkeypatch.setattr(Measurement, "problem_set", problem_set)
    monkeypatch.setattr(plots, "plot_horizon", lambda summary, out: [])  # seconds per report, not under test here
    return state


def _config(out: Path, **overrides: Any) -> ClosedLoopConfig:
    settings = {
        "scenario": SHORT,
        "problems": 5,
        "batch": 2,
        "horizons": [10, 20],
        "robust_blend": 0.0,
        "plants": ["nominal", "perturbed"],
        "workers": 1,
        "out": str(out),
        **overrides,
    }
    return ClosedLoopConfig(**settings)


def _comparable(out: Path) -> dict[str, Any]:
    """The report in ``out`` less what differs between any two runs: wall time, machine, the folder's name."""
    report = json.loads((out / "mpc.json").read_text())
    report["config"].pop("out")
    return {k: v for k, v in report.items() if k not in ("wall_time_s", "machine", "plots")}


def test_an_interrupted_sweep_resumes_to_the_uninterrupted_report(
    tmp_path: Path, fake_episodes: dict[str, Any]
) -> None:
    whole = tmp_path / "whole"
    run_closed_loop(_config(whole))
    every = list(fake_episodes["calls"])
    assert len(every) == 3 * 2 * 2  # batches (0, 1), (2, 3), (4,) x 2 plants x 2 horizons
    fake_episodes["calls"].clear()
    fake_episodes["stop_after"] = 5
    parts = tmp_path / "parts"
    with pytest.raises(Stop):
        run_closed_loop(_config(parts))
    first = list(fake_episodes["calls"])
    assert not (parts / "mpc.json").exists()  # no report until the sweep is whole
    assert len((parts / EPISODES_FILE).read_text().splitlines()) == sum(len(p) for p, _, _ in first) * 4
    cfg = _config(parts)  # the progress bar starts at the episodes of the 5 stored tasks: 2 problems x 4 methods each
    todo, done = closed_loop._pending(
        cfg, EpisodeStore.open(parts, closed_loop.sweep_fingerprint(cfg, get_scenario(SHORT)))
    )
    assert (len(todo), done) == (12 - 5, 5 * 2 * 4)
    fake_episodes["calls"].clear()
    fake_episodes["stop_after"] = None
    run_closed_loop(_config(parts))
    second = fake_episodes["calls"]
    assert not set(first) & set(second) and sorted(first + second) == sorted(every)  # nothing redone, nothing lost
    assert _comparable(parts) == _comparable(whole)
    assert json.loads((parts / "mpc.json").read_text())["complete"] is True
    assert (parts / "mpc_runs.csv").read_text() == (whole / "mpc_runs.csv").read_text()
    assert (parts / "mpc.md").read_text() == (whole / "mpc.md").read_text()
    fake_episodes["calls"].clear()
    run_closed_loop(_config(parts))  # a finished sweep re-run: only the report is written again
    assert fake_episodes["calls"] == []


def test_a_sweep_extends_its_grid_and_refuses_another_configuration(
    tmp_path: Path, fake_episodes: dict[str, Any]
) -> None:
    out = tmp_path / "sweep"
    run_closed_loop(_config(out, problems=4, horizons=[10]))
    fake_episodes["calls"].clear()
    run_closed_loop(_config(out, problems=5, horizons=[10, 20]))
    assert sorted(fake_episodes["calls"]) == sorted(
        [((4,), p, 10) for p in ("nominal", "perturbed")]
        + [(chunk, p, 20) for chunk in ((0, 1), (2, 3), (4,)) for p in ("nominal", "perturbed")]
    )
    report = json.loads((out / "mpc.json").read_text())
    assert len(report["runs"]) == 5 * 2 * 2 * 4
    with pytest.raises(UserError, match=r"another configuration \(seed: 1 here, 0 there\)"):
        run_closed_loop(_config(out, seed=1))
    with pytest.raises(UserError, match=r"mpc\.end_horizon: 20 here, null there"):
        run_closed_loop(_config(out, mpc={"end_horizon": 20}))


def test_a_record_cut_short_is_dropped_and_its_task_run_again(tmp_path: Path, fake_episodes: dict[str, Any]) -> None:
    out = tmp_path / "sweep"
    run_closed_loop(_config(out, problems=2, plants=["nominal"]))
    lines = (out / EPISODES_FILE).read_text().splitlines(keepends=True)
    (out / EPISODES_FILE).write_text("".join(lines[:-1]) + lines[-1][:20])  # the last write cut mid-line
    fake_episodes["calls"].clear()
    run_closed_loop(_config(out, problems=2, plants=["nominal"]))
    assert fake_episodes["calls"] == [((0, 1), "nominal", 20)]  # the task of the lost record, only it
    assert (out / EPISODES_FILE).read_text().endswith("\n")
    assert len(json.loads((out / "mpc.json").read_text())["runs"]) == 2 * 2 * 4


def test_the_store_keeps_nan_and_refuses_a_damaged_line(tmp_path: Path) -> None:
    store = EpisodeStore.open(tmp_path, {"seed": 0})
    store.add([_episode(0, "nominal", 10, "REL-MPC") | {"rel_increment": float("nan")}])
    again = EpisodeStore.open(tmp_path, {"seed": 0})
    (record,) = again.done.values()
    assert record["rel_increment"] != record["rel_increment"]  # nan, as it was
    with open(tmp_path / EPISODES_FILE, "a") as f:
        f.write("not json\n")
    with pytest.raises(UserError, match="line 2, is not an episode record"):
        EpisodeStore.open(tmp_path, {"seed": 0})


def _runs(method: str, horizon: int, increments: list[float], step: float, largest: float) -> list[dict[str, Any]]:
    return [
        {
            "problem": p,
            "plant": "nominal",
            "method": method,
            "horizon": horizon,
            "feasible": inc is not None,
            "rel_increment": float("nan") if inc is None else inc,
            "mean_step_time": step,
            "max_step_time": largest,
        }
        for p, inc in enumerate(increments)
    ]


FT = "R-FT-TTO-MPC[rtg=value]"
FT_10 = [0.10, 0.12, 0.08, 0.10, 0.10]


def test_the_speedup_at_equal_cost_on_a_hand_made_sweep() -> None:
    """REL-MPC@10 and @20 cost clearly more than R-FT-TTO-MPC@10 (+30 points; +5 ± 0.8); @30 within one standard
    error (+0.25 ± 0.75 over the 4 problems both reach, problem 4 missed by REL-MPC@30); steps 7× longer on average,
    6× at their largest. The other way, R-FT-TTO-MPC@10 already matches REL-MPC@30."""
    records = _runs(FT, 10, FT_10, 0.01, 0.05) + _runs(FT, 20, [0.5] * 5, 0.02, 0.1)
    records += _runs("REL-MPC", 10, [x + 0.30 for x in FT_10], 0.03, 0.1)
    rel_20 = [x + d for x, d in zip(FT_10, [0.05, 0.07, 0.03, 0.05, 0.05], strict=True)]
    rel_30 = [x + d for x, d in zip(FT_10[:4], [0.01, -0.01, 0.02, -0.01], strict=True)]
    records += _runs("REL-MPC", 20, rel_20, 0.05, 0.2) + _runs("REL-MPC", 30, [*rel_30, None], 0.07, 0.3)
    rel, ft = equal_cost(records)
    assert (rel["moving"], rel["fixed"], rel["horizon"]) == ("REL-MPC", f"{'R-FT-TTO-MPC'}@10", 30)
    assert rel["paired"]["mean"] == pytest.approx(0.25) and rel["paired"]["se"] == pytest.approx(0.75)
    assert rel["paired"]["n"] == 4 and rel["goals"] == (4, 5, 5)
    assert rel["mean_ratio"] == pytest.approx(7.0) and rel["largest_ratio"] == pytest.approx(6.0)
    assert (ft["moving"], ft["fixed"], ft["horizon"]) == ("R-FT-TTO-MPC", "REL-MPC@30", 10)
    assert ft["mean_ratio"] == pytest.approx(7.0) and ft["paired"]["mean"] == pytest.approx(-0.25)
    table = format_equal_cost([rel, ft])
    assert "| nominal | REL-MPC | R-FT-TTO-MPC@10 | 30 | 0.25 ± 0.75" in table and "| 7×, 6× |" in table


def test_no_matching_horizon_is_said() -> None:
    records = _runs(FT, 10, FT_10, 0.01, 0.05) + _runs("REL-MPC", 10, [x + 0.3 for x in FT_10], 0.03, 0.1)
    rel, ft = equal_cost(records)
    assert rel["horizon"] is None and rel["why"] == "H = 10 tried"
    assert ft["horizon"] is None and ft["why"] == "REL-MPC@30 did not run"
    assert "no H matches (REL-MPC@30 did not run)" in format_equal_cost([rel, ft])


@pytest.mark.slow
def test_real_episodes_resume_to_the_same_report(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The baselines' real episodes (3 steps each) on the short scenario: stopped after the first stored task, the
    sweep resumes with the other and reports the runs of an uninterrupted sweep, step times aside."""
    settings = {
        "scenario": SHORT,
        "problems": 2,
        "batch": 1,
        "horizons": [10],
        "plants": ["nominal"],
        "max_steps": 3,
        "workers": 1,
        "robust_blend": 0.0,
    }
    monkeypatch.setattr(plots, "plot_horizon", lambda summary, out: [])
    whole = run_closed_loop(ClosedLoopConfig(**settings, out=str(tmp_path / "whole")))
    add = EpisodeStore.add

    def add_then_stop(self: EpisodeStore, records: Any) -> None:
        add(self, records)
        raise Stop

    monkeypatch.setattr(EpisodeStore, "add", add_then_stop)
    with pytest.raises(Stop):
        run_closed_loop(ClosedLoopConfig(**settings, out=str(tmp_path / "parts")))
    monkeypatch.setattr(EpisodeStore, "add", add)
    parts = run_closed_loop(ClosedLoopConfig(**settings, out=str(tmp_path / "parts")))

    def untimed(runs: list[dict[str, Any]]) -> str:  # as text: nan equals nan
        return json.dumps([{k: v for k, v in r.items() if k not in ("mean_step_time", "max_step_time")} for r in runs])

    assert untimed(parts["runs"]) == untimed(whole["runs"])
    assert len(parts["runs"]) == 2 * len(methods_for({}, 0.0))


def test_a_report_that_fails_midway_leaves_no_complete_report(
    tmp_path: Path, fake_episodes: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The earlier complete mpc.json is removed before the new tables are written: a failure in between (here in
    the plots) leaves a folder that no consumer reads as a report."""
    out = tmp_path / "sweep"
    run_closed_loop(_config(out, problems=2, plants=["nominal"], horizons=[10]))
    assert json.loads((out / "mpc.json").read_text())["complete"] is True

    def broken(summary: Any, out: Any) -> Any:
        raise Stop

    monkeypatch.setattr(plots, "plot_horizon", broken)
    with pytest.raises(Stop):
        run_closed_loop(_config(out, problems=3, plants=["nominal"], horizons=[10]))
    assert not (out / "mpc.json").exists() and (out / "mpc_runs.csv").is_file()
