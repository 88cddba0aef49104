"""The paper's Fig. 5 and Fig. 6 as we measure them: one figure per plant, one column per scenario (a closed-loop
sweep report of ``ttompc evaluate mpc`` each), drawn by ``make figures`` (``ttompc.evaluation.figures``).

Rows, each against the planning horizon H, for the methods of ``PAPER_METHODS`` the reports ran (a model method's rtg
suffix, e.g. ``[rtg=value]``, ignored when matching):

1. the paper's normalised cost increment (J − LB)/(maxcost − LB) over each method's feasible runs, mean ± s.e.
   (``metrics.normalized_cost``: per problem, its worst feasible run over every method and H = 1);
2. (J − J_REL)/J_REL over each method's feasible runs (``plots.horizon_cost_panel``: feasible/runs marked);
3. the failure rate: runs that missed the goal or violated a constraint, in % of the runs (counted apart from the
   costs above);
4. and 5. Fig. 6: the largest step of each episode (the paper's measure) and its mean step, each averaged over the
   episodes ± s.e. (``step_times``), log scale, titled with the machine and its load (the report's ``machine``).

The footer names each column's report: its command, and the machine, load and workers its step times ran on.
"""

from __future__ import annotations

import textwrap
from collections.abc import Sequence
from typing import Any

import numpy as np

from ttompc.errors import UserError
from ttompc.evaluation.machine import machine_label
from ttompc.evaluation.plots import horizon_axis, horizon_cost_panel, line_style
from ttompc.model_slots import MODEL_SLOTS
from ttompc.mpc.methods import METHODS, base_method

# the paper's four methods, our headline (the robust fine-tuned method) and the ceiling
PAPER_METHODS = ("REL-MPC", "DIST-MPC", "TTO-MPC", "FT-TTO-MPC", "R-FT-TTO-MPC", "ORACLE-MPC")
STEP_KINDS = {"max_step_time": "largest step of an episode (the paper's Fig. 6)", "mean_step_time": "mean step"}


def _style(method: str) -> int:
    """A method's line style (``plots.line_style``): its place in ``PAPER_METHODS``, the same in every panel."""
    return PAPER_METHODS.index(base_method(method))


def model_label(method: str, config: dict[str, Any]) -> str:
    """A method's legend label: the method, and for a model's method (TTO…, FT-TTO…, their MPC variants) the model
    the report ran it with."""
    entry = METHODS.get(base_method(method))  # a closed-loop method; a warm-start report names its methods by slot
    slot = entry.model if entry is not None else method
    model = config.get(MODEL_SLOTS.get(slot or "", ""))
    return f"{method} ({model})" if model else method


def paper_rows(report: dict[str, Any], plant: str = "nominal") -> list[dict[str, Any]]:
    """The ``summary`` rows of ``PAPER_METHODS`` on ``plant``, in that method order then by H; raises ``UserError``
    if there are none."""
    rows = [r for r in report["summary"] if r["plant"] == plant and base_method(r["method"]) in PAPER_METHODS]
    if not rows:
        raise UserError(f"the closed-loop report has no run of {', '.join(PAPER_METHODS)} on the {plant} plant")
    return sorted(rows, key=lambda r: (PAPER_METHODS.index(base_method(r["method"])), r["horizon"]))


def step_times(report: dict[str, Any], plant: str = "nominal") -> list[dict[str, Any]]:
    """Fig. 6's points from the report's ``runs``: per method of ``paper_rows`` and H, the number of episodes and,
    for each episode statistic of ``STEP_KINDS`` (its largest and its mean step time [s]), the mean and standard
    error over the episodes."""
    out = []
    for row in paper_rows(report, plant):
        runs = [
            r
            for r in report["runs"]
            if r["plant"] == plant and r["method"] == row["method"] and r["horizon"] == row["horizon"]
        ]
        point: dict[str, Any] = {"method": row["method"], "horizon": row["horizon"], "runs": len(runs)}
        for key in STEP_KINDS:
            times = np.array([r[key] for r in runs])
            se = float(times.std(ddof=1) / np.sqrt(len(times))) if len(times) > 1 else float("nan")
            point[key] = {"mean": float(times.mean()), "se": se}
        out.append(point)
    return out


def _lines(ax: Any, points: Sequence[dict[str, Any]], value: Any, labels: dict[str, str]) -> None:
    """One error-bar line per method of ``points`` (rows with method and horizon): ``value(point)`` → (y, s.e.)."""
    for method in dict.fromkeys(p["method"] for p in points):
        ps = [p for p in points if p["method"] == method]
        ys, ses = zip(*(value(p) for p in ps), strict=True)
        style = {**line_style(_style(method)), "marker": "o", "markersize": 4, "markevery": 1}
        xs = [p["horizon"] for p in ps]
        ax.errorbar(xs, ys, yerr=np.nan_to_num(ses), capsize=3, **style, label=labels[method])
    horizon_axis(ax, list(points))


def _log_ms(ax: Any) -> None:
    from matplotlib.ticker import FuncFormatter

    ax.set_yscale("log")
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))  # 10, 100: not 10^1, 10^2
    ax.yaxis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:g}" if f"{v:g}"[0] in "25" else ""))


def horizon_figure(reports: Sequence[dict[str, Any]], plant: str) -> tuple[Any, str]:
    """The figure of the module doc for ``plant``, one column per report (of ``paper_rows``), and its footer text
    (each report's command and machine, ``_source``)."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(5, len(reports), figsize=(5 * len(reports), 17), squeeze=False)
    for col, report in zip(axes.T, reports, strict=True):
        rows, config = paper_rows(report, plant), report["config"]
        labels = {r["method"]: model_label(r["method"], config) for r in rows}
        name, n = report["scenario"]["name"], config["problems"]
        normed = [r for r in rows if "paper_norm" in r]
        _lines(col[0], normed, lambda r: (r["paper_norm"]["mean"], r["paper_norm"]["se"]), labels)
        col[0].set_title(f"{name}, {n} problems ({report['protocol']['name']})", fontsize=10)
        col[0].set_ylabel("(J − LB)/(maxcost − LB)\nof feasible runs (worst = 1)")
        col[0].legend(fontsize=7)
        horizon_cost_panel(col[1], rows, labels, {r["method"]: _style(r["method"]) for r in rows})
        col[1].get_legend().remove()
        _lines(col[2], rows, lambda r: (100 * (1 - r["feasible"] / r["runs"]), np.nan), labels)
        col[2].set_ylabel("runs that missed the goal or\nviolated a constraint [%]")
        col[2].set_ylim(-5, 105)
        for ax, key in zip(col[3:], STEP_KINDS, strict=True):
            _lines(ax, step_times(report, plant), lambda p, k=key: (1e3 * p[k]["mean"], 1e3 * p[k]["se"]), labels)
            _log_ms(ax)
            ax.set_ylabel(f"{STEP_KINDS[key]} [ms]\n(mean ± s.e. over episodes)", fontsize=8)
        col[3].set_title(f"step time: observe + warm start + solves, CPU\n{_machine(report)}", fontsize=8)
    title = f"Closed loop vs planning horizon H, {plant} plant: cost (Fig. 5, rows 1–3) "
    title += "and step time (Fig. 6, rows 4–5)"
    fig.suptitle("\n".join(textwrap.wrap(title, 12 * 5 * len(reports))), fontsize=11)  # ~12 characters per inch
    return fig, "From " + "; ".join(_source(r) for r in reports) + "."


def _machine(report: dict[str, Any]) -> str:
    """What a report's step times ran on: the machine, its load and the workers (``machine.machine_label``)."""
    return f"{machine_label(report.get('machine'))}, workers={report['config'].get('workers', '?')}"


def _source(report: dict[str, Any]) -> str:
    """A report's part of the footer: its scenario, its command and what its step times ran on."""
    return f"{report['scenario']['name']}: `{report['command']}` ({_machine(report)})"
