"""The README's figures (``ttompc.evaluation.figures``): drawn from tiny synthetic reports built the way the
``ttompc evaluate`` reports are, they plot the reports' numbers, name the command that reproduces each report, and
write non-empty PNG images."""

from __future__ import annotations

import shlex
from dataclasses import asdict
from pathlib import Path
from typing import Any

import mpc_fakes
import numpy as np
import pytest

from ttompc.config import command_config, to_container
from ttompc.errors import UserError
from ttompc.evaluation import figures, horizon_figures
from ttompc.evaluation.closed_loop import ClosedLoopConfig
from ttompc.evaluation.closed_loop_report import summarize
from ttompc.evaluation.metrics import improvement_by_threshold, write_json
from ttompc.evaluation.reproduce import report_command
from ttompc.evaluation.warmstart import WarmStartConfig, method_summary

METHODS = ("REL-MPC", "DIST-MPC", "PLAN-ONCE", "ORACLE-MPC", "TTO-MPC", "R-TTO-MPC")
METHODS += ("FT-TTO-MPC[rtg=value]", "R-FT-TTO-MPC[rtg=value]")


def mpc_report(scenario: str = "freeflyer") -> dict[str, Any]:
    """Three problems at H = 10 and 20 on the nominal plant, every method of a model run; TTO-MPC misses the goal
    on problems 0 and 1 at H = 10. Marked complete, as ``ttompc evaluate mpc`` writes it."""
    rng = np.random.default_rng(0)
    runs = []
    for problem in range(3):
        for H in (10, 20):
            for i, method in enumerate(METHODS):
                feasible = not (method == "TTO-MPC" and H == 10 and problem < 2)
                cost = 1.0 + 0.1 * i + 0.01 * problem + (0.05 if H == 10 else 0.0)
                runs.append(
                    {
                        "problem": problem,
                        "method": method,
                        "horizon": H,
                        "plant": "nominal",
                        "cost": cost,
                        "rel_cost": 1.0,
                        "feasible": feasible,
                        "rel_increment": cost - 1.0 if feasible else float("nan"),
                        "target_change": 0.1,
                        "mean_step_time": float(rng.uniform(0.001, 0.01)),
                        "max_step_time": float(rng.uniform(0.01, 0.1)),
                        "fallbacks": 0,
                        "terminal_error": 0.0 if feasible else 0.5,
                        "mean_iterations": 1.0,
                        "mean_iterations_solved": 1.0,
                        "complete": True,
                    }
                )
    config = asdict(ClosedLoopConfig(model="tto-x", ft_model="ft-y", horizons=[10, 20], problems=3, seed=7, workers=1))
    command = report_command("mpc", config, ClosedLoopConfig())
    return {
        "config": config,
        "command": command,
        "scenario": {"name": scenario},
        "protocol": {"name": "paper"},
        "summary": summarize(runs),
        "runs": runs,
        "complete": True,
    }


def warmstart_report() -> dict[str, Any]:
    """Four problems, REL and two models and the oracle, nonconvexity 0.25 steps apart."""
    problems = []
    for k in range(4):
        row: dict[str, Any] = {"problem": k, "rel_cost": 1.0, "nonconvexity": 0.25 * k}
        for m, (gap, iterations) in {"REL": (0.4, 6), "TTO": (0.3, 5), "FT-TTO": (0.35, 7), "ORACLE": (0.2, 6)}.items():
            row |= {
                f"{m}_success": True,
                f"{m}_cost": 1.0 + gap + 0.1 * k,
                f"{m}_iterations": iterations + k,
                f"{m}_suboptimality": gap + 0.1 * k,
                f"{m}_time": 0.1,
            }
        problems.append(row)
    config = asdict(WarmStartConfig(model="tto-x", ft_model="ft-y", problems=4, seed=7, workers=1))
    return {
        "config": config,
        "command": report_command("warmstart", config, WarmStartConfig()),
        "scenario": {"name": "freeflyer"},
        "methods": method_summary(problems, ["REL", "TTO", "FT-TTO", "ORACLE"]),
        "thresholds": improvement_by_threshold(problems, ["TTO", "FT-TTO", "ORACLE"], "REL", [0.0, 0.5, 0.9]),
        "problems": problems,
        "complete": True,
    }


def test_the_paper_methods_are_picked_in_the_papers_order() -> None:
    rows = horizon_figures.paper_rows(mpc_report())
    names = [r["method"] for r in rows]
    assert list(dict.fromkeys(names)) == [
        "REL-MPC",
        "DIST-MPC",
        "TTO-MPC",
        "FT-TTO-MPC[rtg=value]",
        "R-FT-TTO-MPC[rtg=value]",
        "ORACLE-MPC",
    ]
    assert [r["horizon"] for r in rows] == [10, 20] * 6
    with pytest.raises(UserError, match="perturbed plant"):
        horizon_figures.paper_rows(mpc_report(), "perturbed")


def test_step_times_average_each_episodes_largest_and_mean_step() -> None:
    report = mpc_report()
    for point in horizon_figures.step_times(report):
        assert point["runs"] == 3
        for key in ("max_step_time", "mean_step_time"):
            times = [
                r[key] for r in report["runs"] if r["method"] == point["method"] and r["horizon"] == point["horizon"]
            ]
            assert point[key]["mean"] == pytest.approx(np.mean(times))
            assert point[key]["se"] == pytest.approx(np.std(times, ddof=1) / np.sqrt(3))


def test_warmstart_bars_are_the_reports_improvements() -> None:
    report = warmstart_report()
    bars = figures.warmstart_bars(report)
    assert bars["methods"] == ["TTO", "FT-TTO", "ORACLE"] and bars["thresholds"] == [0.0, 0.5, 0.9]
    assert bars["counts"] == [4, 2, 0]
    assert bars["subopt"]["TTO"][0] == pytest.approx(100 * (1 - 0.45 / 0.55))  # mean gaps over the four problems
    assert bars["iterations"]["FT-TTO"][1] == pytest.approx(100 * (1 - 9.5 / 8.5))
    assert np.isnan(bars["subopt"]["TTO"][2])  # no problem at or above 0.9


@pytest.mark.parametrize("kind", ["mpc", "warmstart"])
def test_the_footer_command_reproduces_the_reports_settings(kind: str) -> None:
    """Parsed back by the command's own parser and loader, the line gives the settings the report recorded (but
    INERT), in the form the zoo's cards print (models as flags, then the protocol's keys)."""
    from ttompc.cli import build_parser
    from ttompc.commands.evaluate import _FLAGS
    from ttompc.evaluation.reproduce import INERT

    report = mpc_report() if kind == "mpc" else warmstart_report()
    config = report["config"]
    if kind == "mpc":
        config["mpc"] = {"end_horizon": 20}
        config["plant"] = {**config["plant"], "process_std": 0.005}  # a nested setting, as a dotted key
    line = report_command(kind, config, ClosedLoopConfig() if kind == "mpc" else WarmStartConfig())
    assert line.startswith(f"ttompc evaluate {kind} --model tto-x --ft-model ft-y problems=")
    assert "workers" not in line and "out=" not in line and "seed=7" in line
    argv = shlex.split(line)[1:]
    schema = ClosedLoopConfig if kind == "mpc" else WarmStartConfig
    parsed = to_container(command_config(schema, build_parser(argv).parse_args(argv), _FLAGS))
    assert {k: v for k, v in parsed.items() if k not in INERT} == {k: v for k, v in config.items() if k not in INERT}
    if kind == "mpc":
        assert "mpc.end_horizon=20 plant.process_std=0.005" in line


def test_the_figures_plot_the_reports_numbers(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """One column per scenario's report; rows: the paper's normalised cost, (J − J_REL)/J_REL, the failure rate and
    the largest and mean step; the footer names every report's command, machine, load and workers."""
    reports = [mpc_report("freeflyer"), mpc_report("quadrotor")]
    reports[1]["machine"] = {"cpu": "CPU X", "cpus": 2, "load_average": [3, 2, 1.2], "load_average_end": [1, 1, 2.5]}
    fig, text = horizon_figures.horizon_figure(reports, "nominal")
    axes = np.array(fig.axes[:10]).reshape(5, 2)  # subplots first, in row order
    assert text == (
        f"From freeflyer: `{reports[0]['command']}` (machine not recorded, workers=1); "
        f"quadrotor: `{reports[1]['command']}` (CPU X, 2 cores, load 2.5, workers=1)."
    )

    def line(ax: Any, label: str) -> np.ndarray:  # the y data of the error bars labelled ``label``
        (found,) = [c.lines[0] for c in ax.containers if c.get_label() == label]
        return np.asarray(found.get_ydata(), dtype=float)

    for col, report in zip(axes.T, reports, strict=True):
        rows = horizon_figures.paper_rows(report)
        ft = "FT-TTO-MPC[rtg=value] (ft-y)"
        norm = [r["paper_norm"]["mean"] for r in rows if r["method"] == "FT-TTO-MPC[rtg=value]"]
        np.testing.assert_allclose(line(col[0], ft), norm)
        increments = [100 * r["rel_increment"]["mean"] for r in rows if r["method"] == "TTO-MPC"]
        np.testing.assert_allclose(line(col[1], "TTO-MPC (tto-x)"), increments)
        np.testing.assert_allclose(line(col[2], "TTO-MPC (tto-x)"), [100 * 2 / 3, 0.0])  # 2 of 3 missed at H = 10
        for ax, key in ((col[3], "max_step_time"), (col[4], "mean_step_time")):
            steps = [1e3 * p[key]["mean"] for p in horizon_figures.step_times(report) if p["method"] == "REL-MPC"]
            np.testing.assert_allclose(line(ax, "REL-MPC"), steps)
    import matplotlib.pyplot as plt

    plt.close(fig)


def test_make_figures_writes_the_images_and_the_equal_cost_table(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """As the reports are written (``write_json``: nan as null), through the command line: one closed-loop figure
    per plant the reports share, from two scenarios' reports, then the speedup at equal cost of both."""
    import matplotlib.image

    bundle = mpc_fakes.tiny_planner().save(tmp_path / "bundle")
    write_json(tmp_path / "ff.json", mpc_report("freeflyer"))
    write_json(tmp_path / "quad.json", mpc_report("quadrotor"))
    write_json(tmp_path / "warmstart.json", warmstart_report())
    mpc = [str(tmp_path / "ff.json"), str(tmp_path / "quad.json")]
    args = ["--mpc", *mpc, "--warmstart", str(tmp_path / "warmstart.json")]
    out, table = tmp_path / "figures", tmp_path / "docs" / "equal-cost.md"
    argv = [*args, "--out", str(out), "--model", str(bundle), "--seed", "3", "--problems", "0", "--table", str(table)]
    assert figures.main(argv) == 0
    printed = capsys.readouterr().out
    names = [*figures.FILES, figures.horizon_file("nominal")]
    assert printed.split("\n")[:4] == [*(str(out / name) for name in names), str(table)]
    assert "Speedup at equal cost" in printed and "| freeflyer | nominal | REL-MPC |" in printed
    written = table.read_text()
    assert written.startswith("# Speedup at equal cost") and f"--mpc {' '.join(mpc)} ... --table {table}" in written
    assert figures.equal_cost_table(mpc) in written  # the printed table, as the docs show it
    for name in names:
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        height, width, _ = matplotlib.image.imread(out / name).shape
        assert height > 200 and width > 200


def test_a_missing_report_is_one_line_naming_the_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = figures.main(["--mpc", str(tmp_path / "none.json"), "--warmstart", str(tmp_path / "none.json")])
    assert rc == 2 and "no report at" in capsys.readouterr().err


def test_an_incomplete_report_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A report not marked complete (its run stopped before the end, or an older ttompc) draws no figure."""
    write_json(tmp_path / "mpc.json", {k: v for k, v in mpc_report().items() if k != "complete"})
    write_json(tmp_path / "warmstart.json", warmstart_report())
    rc = figures.main(["--mpc", str(tmp_path / "mpc.json"), "--warmstart", str(tmp_path / "warmstart.json")])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1
    assert f"{tmp_path / 'mpc.json'} is not a complete report" in err


def test_a_report_without_its_command_is_refused_naming_the_fix(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A report written before reports recorded their ``command`` (the footer's) is one line: the file, and the
    command to re-run."""
    old = {k: v for k, v in mpc_report().items() if k != "command"}
    write_json(tmp_path / "mpc.json", old)
    write_json(tmp_path / "warmstart.json", warmstart_report())
    rc = figures.main(["--mpc", str(tmp_path / "mpc.json"), "--warmstart", str(tmp_path / "warmstart.json")])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1
    assert f"{tmp_path / 'mpc.json'} records no command" in err
    assert "re-run `ttompc evaluate mpc ...` to write a report with its command" in err


@pytest.mark.parametrize("kind", ["mpc", "warmstart"])
def test_the_written_report_records_the_command_of_its_config(kind: str, tmp_path: Path) -> None:
    """``ttompc evaluate``'s reports carry their ``command``: ``report_command`` of the config they record."""
    import time

    from ttompc.evaluation.closed_loop_report import write_report
    from ttompc.evaluation.warmstart import run_warmstart
    from ttompc.scenarios import get_scenario

    out = tmp_path / "report"  # a folder of its own: a report folder holds nothing else (``claim_report``)
    if kind == "mpc":
        cfg = ClosedLoopConfig(model="tto-x", ft_model="ft-y", scenario="freeflyer", horizons=[10, 20], problems=3)
        out.mkdir()
        write_report(cfg, get_scenario("freeflyer"), mpc_report()["runs"], out, 1, time.perf_counter())
    else:
        bundle = mpc_fakes.tiny_planner().save(tmp_path / "bundle")
        run_warmstart(
            WarmStartConfig(
                model=str(bundle),
                scenario=mpc_fakes.FreeFlyerShort.name,
                problems=1,
                workers=1,
                oracle_detours=0,
                out=str(out),
            )
        )
    report = figures.load_report(out / f"{kind}.json", kind)
    defaults = ClosedLoopConfig() if kind == "mpc" else WarmStartConfig()
    assert report["command"] == report_command(kind, report["config"], defaults)
    assert report["command"].startswith(f"ttompc evaluate {kind} --model ")


def test_a_method_keeps_its_style_in_every_panel_whatever_ran() -> None:
    """A report of the baselines only: ORACLE-MPC is drawn in the same colour in the cost, failure and step panels
    (its place in the paper's methods), not by its place among the methods that ran."""
    import matplotlib.pyplot as plt
    from matplotlib.colors import to_hex

    report = mpc_report()
    baselines = ("REL-MPC", "DIST-MPC", "ORACLE-MPC")
    report["summary"] = [r for r in report["summary"] if r["method"] in baselines]
    report["runs"] = [r for r in report["runs"] if r["method"] in baselines]
    fig, _ = horizon_figures.horizon_figure([report], "nominal")
    colours = {
        to_hex(c.lines[0].get_color()) for ax in fig.axes[:5] for c in ax.containers if c.get_label() == "ORACLE-MPC"
    }
    assert colours == {to_hex(f"C{horizon_figures.PAPER_METHODS.index('ORACLE-MPC')}")}
    plt.close(fig)
