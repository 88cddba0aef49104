"""The README's figures (``make figures``): a planned trajectory and the paper's Fig. 4–6 as we measure them, each
drawn from a report that a stated ``ttompc evaluate`` command writes, and each carrying that command in its footer
(the report's ``command``: ``ttompc.evaluation.reproduce.report_command`` of the settings it records).

* ``planned_trajectory.png``: held-out non-convex problems (``--problems`` of the evaluation stream of ``--seed``),
  computed here with the evaluation protocol's per-problem step (``warmstart.evaluate_problem``): keep-out zones,
  the REL path (the convex relaxation, a lower bound on the cost that may cross them), the model's warm start, SCP
  from REL and SCP from the model's warm start, each with its cost.
* ``warmstart.png`` (Fig. 4) from ``warmstart.json`` of ``ttompc evaluate warmstart``: % improvement over the REL
  warm start in suboptimality (J − J_REL) and SCP iterations, over problems at or above each non-convexity factor,
  for the TTO and FT-TTO models and the oracle's best optimum (the ceiling), with the problems behind each bar.
* ``closed_loop_cost.png`` (Fig. 5) from ``mpc.json`` of ``ttompc evaluate mpc``: the paper's four methods (REL-MPC,
  DIST-MPC, TTO-MPC, FT-TTO-MPC; under ``protocol=recommended`` the model methods carry their rtg mode in their name)
  vs the planning horizon H on one plant: the paper's normalised cost increment (left) and (J − J_REL)/J_REL over
  each method's feasible runs with feasible/runs marked (right).
* ``step_time.png`` (Fig. 6) from the same report: the mean over episodes of each episode's largest MPC step time
  (the paper's measure; it includes one-off costs such as the first solve of a window shape) and of its mean step
  time, ± s.e., vs H (CPU seconds: an episode's share of the batched rollout plus its own solves, as the report
  records).

    python -m ttompc.evaluation.figures --mpc MPC.json --warmstart WARMSTART.json --out docs/figures

``make figures`` runs the two ``ttompc evaluate`` commands whose reports these are (the Makefile names them) when
the reports are missing, then this.
"""

from __future__ import annotations

import argparse
import json
import sys
import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ttompc.errors import UserError
from ttompc.evaluation.plots import Panel, horizon_axis, horizon_cost_panel, line_style, trajectory_figure

PAPER_METHODS = ("REL-MPC", "DIST-MPC", "TTO-MPC", "FT-TTO-MPC")
WARMSTART_METHODS = ("TTO", "FT-TTO", "ORACLE")
MODEL_KEYS = {"TTO": "model", "FT-TTO": "ft_model"}  # method -> the config key naming its model
FILES = ("planned_trajectory.png", "warmstart.png", "closed_loop_cost.png", "step_time.png")
# The planned problems of the stream of seed 4242 (the zoo cards'): 0, the first, on which SCP from REL and from
# freeflyer-ft-tto-v5 reach the same optimum (as on 68 of the 100 problems of the warm-start report that `make figures`
# runs); 7, the first on which SCP from the model reaches a cheaper one (21 of 100; 11 the other way).
PROBLEMS = (0, 7)


def load_report(path: str | Path, kind: str) -> dict[str, Any]:
    """The report at ``path``: ``kind`` "mpc" (``mpc.json``, with ``summary`` and ``runs``) or "warmstart"
    (``warmstart.json``, with ``methods`` and ``thresholds``), the nulls of those sections read as nan; raises
    ``UserError`` for a missing file, another kind of report or a report without its ``command`` (the footer's)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"no report at {path}", f"run `ttompc evaluate {kind} ...` first (see `make figures`)")
    report: dict[str, Any] = json.loads(path.read_text())
    need = ("summary", "runs") if kind == "mpc" else ("methods", "thresholds")
    if any(key not in report for key in need):
        raise UserError(f"{path} is not a `ttompc evaluate {kind}` report (it lacks {' and '.join(need)})")
    if not report.get("command"):
        raise UserError(
            f"{path} records no command (it was written by an older ttompc)",
            f"re-run `ttompc evaluate {kind} ...` to write a report with its command (`make figures` runs it when "
            "the report is missing)",
        )
    return {**report, **{key: _nan(report[key]) for key in need}}


def _nan(data: Any) -> Any:
    """``data`` with every null turned back into the nan it was written from (``metrics.write_json``)."""
    if isinstance(data, dict):
        return {k: _nan(v) for k, v in data.items()}
    if isinstance(data, list):
        return [_nan(v) for v in data]
    return float("nan") if data is None else data


def model_label(method: str, config: dict[str, Any]) -> str:
    """A method's legend label: the method, and for a model's method (TTO…, FT-TTO…, their MPC variants) the model
    the report ran it with."""
    base = method.removeprefix("R-").split("-MPC")[0]
    model = config.get(MODEL_KEYS.get(base, ""))
    return f"{method} ({model})" if model else method


def paper_rows(report: dict[str, Any], plant: str = "nominal") -> list[dict[str, Any]]:
    """The ``summary`` rows of ``PAPER_METHODS`` on ``plant`` (a model method's rtg suffix, e.g. ``[rtg=value]``,
    ignored when matching), in that method order then by H; raises ``UserError`` if there are none."""

    def base(method: str) -> str:
        return method.split("[")[0]

    rows = [r for r in report["summary"] if r["plant"] == plant and base(r["method"]) in PAPER_METHODS]
    if not rows:
        raise UserError(f"the closed-loop report has no run of {', '.join(PAPER_METHODS)} on the {plant} plant")
    return sorted(rows, key=lambda r: (PAPER_METHODS.index(base(r["method"])), r["horizon"]))


STEP_KINDS = {"max_step_time": "largest step of an episode (the paper's Fig. 6)", "mean_step_time": "mean step"}


def step_times(report: dict[str, Any], plant: str = "nominal") -> list[dict[str, Any]]:
    """Fig. 6's points from the report's ``runs``: per method of ``paper_rows`` and H, the number of episodes and,
    for each episode statistic of ``STEP_KINDS`` (its largest and its mean step time [s]), the mean and standard
    error over the episodes."""
    out = []
    for row in paper_rows(report, plant):
        runs = [r for r in report["runs"]
                if r["plant"] == plant and r["method"] == row["method"] and r["horizon"] == row["horizon"]]  # fmt: skip
        point: dict[str, Any] = {"method": row["method"], "horizon": row["horizon"], "runs": len(runs)}
        for key in STEP_KINDS:
            times = np.array([r[key] for r in runs])
            se = float(times.std(ddof=1) / np.sqrt(len(times))) if len(times) > 1 else float("nan")
            point[key] = {"mean": float(times.mean()), "se": se}
        out.append(point)
    return out


def warmstart_bars(report: dict[str, Any]) -> dict[str, Any]:
    """Fig. 4's bars from a warm-start report: ``methods`` (those of ``WARMSTART_METHODS`` it ran), ``thresholds``,
    ``counts`` (problems at or above each threshold solved by every method) and per method its ``subopt`` and
    ``iterations`` improvement over REL [%] per threshold (nan where no problem qualifies)."""
    ran = {e["method"] for e in report["methods"]}
    methods = [m for m in WARMSTART_METHODS if m in ran]
    rows = report["thresholds"]
    return {
        "methods": methods,
        "thresholds": [r["threshold"] for r in rows],
        "counts": [r["count"] for r in rows],
        "subopt": {m: [_num(r.get(f"{m}_subopt_improvement")) for r in rows] for m in methods},
        "iterations": {m: [_num(r.get(f"{m}_iterations_improvement")) for r in rows] for m in methods},
    }


def _num(v: Any) -> float:
    return float("nan") if v is None else float(v)


def _footer(fig: Any, text: str) -> None:
    """``text`` wrapped under the figure's axes (about 15 characters per inch at font size 7, lines 1.35 font sizes
    apart), the axes laid out above it."""
    lines = textwrap.wrap(text, int(15 * fig.get_figwidth()))
    height = (len(lines) * 7 * 1.35 / 72 + 0.1) / fig.get_figheight()  # inches -> figure fraction
    fig.tight_layout(rect=(0, height, 1, 1))
    fig.text(0.01, 0.01, "\n".join(lines), fontsize=7, color="0.3", va="bottom")


def _save_with_footer(fig: Any, path: Path, text: str) -> Path:
    import matplotlib.pyplot as plt

    _footer(fig, text)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def warmstart_figure(report: dict[str, Any], path: Path) -> Path:
    """Fig. 4 (``warmstart_bars``) to ``path``, its command in the footer."""
    import matplotlib.pyplot as plt

    bars, config = warmstart_bars(report), report["config"]
    methods = bars["methods"]
    fig, axes = plt.subplots(2, 1, figsize=(7, 5.5), sharex=True)
    x = np.arange(len(bars["thresholds"]))
    width = 0.8 / max(len(methods), 1)
    for ax, key, label in ((axes[0], "subopt", "suboptimality gap"), (axes[1], "iterations", "SCP iterations")):
        for j, m in enumerate(methods):
            oracle = m == "ORACLE"
            ax.bar(
                x + (j - (len(methods) - 1) / 2) * width,
                bars[key][m],
                width,
                color="0.75" if oracle else f"C{j}",
                hatch="//" if oracle else None,
                label="ORACLE (best optimum of several starts: the ceiling)" if oracle else model_label(m, config),
            )
        ax.axhline(0, color="k", lw=0.8)
        ax.set_ylabel(f"{label}:\nimprovement over REL [%]")
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=7)
    axes[0].set_title(
        f"Open-loop warm starts, {report['scenario']['name']}: full-horizon SCP from each warm start vs from REL",
        fontsize=9,
    )
    axes[1].set_xticks(x, [f"≥ {c:.1f}\n({n})" for c, n in zip(bars["thresholds"], bars["counts"], strict=True)])
    axes[1].set_xlabel("non-convexity factor (problems)")
    return _save_with_footer(fig, path, f"From `{report['command']}`.")


def cost_figure(report: dict[str, Any], path: Path, plant: str = "nominal") -> Path:
    """Fig. 5 to ``path``: the paper's normalised cost increment (left; over the problems every method of the
    report ran feasibly at every H, DIST-MPC's worst H = 1) and ``horizon_cost_panel`` (right, with the legend) of
    ``paper_rows``, its command in the footer."""
    import matplotlib.pyplot as plt

    rows, config = paper_rows(report, plant), report["config"]
    methods = list(dict.fromkeys(r["method"] for r in rows))
    labels = {m: model_label(m, config) for m in methods}
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.2))
    normed = [r for r in rows if "paper_norm" in r]
    for i, m in enumerate(methods):
        rs = [r for r in normed if r["method"] == m]
        left.errorbar(
            [r["horizon"] for r in rs],
            [r["paper_norm"]["mean"] for r in rs],
            yerr=[np.nan_to_num(r["paper_norm"]["se"]) for r in rs],
            capsize=3,
            **{**line_style(i), "marker": "o", "markersize": 5, "markevery": 1},
            label=labels[m],
        )
    n = max((r["paper_problems"] for r in normed), default=0)
    left.set_title(
        f"the paper's normalisation, over the {n} problems\nevery method of the report ran feasibly at every H"
        if n
        else "the paper's normalisation: undefined\n(no problem every method ran feasibly)",
        fontsize=9,
    )
    left.set_ylabel("normalised cost increment\n(DIST-MPC at its worst H = 1)")
    horizon_axis(left, rows)
    horizon_cost_panel(right, rows, labels)
    right.set_title(f"each method's feasible runs,\n{plant} plant, {config['problems']} problems", fontsize=9)
    fig.suptitle(
        f"Closed-loop cost vs planning horizon, {report['scenario']['name']} (protocol {report['protocol']['name']})",
        fontsize=10,
    )
    return _save_with_footer(fig, path, f"From `{report['command']}`.")


def step_time_figure(report: dict[str, Any], path: Path, plant: str = "nominal") -> Path:
    """Fig. 6 (``step_times``) to ``path``, one log-scale panel per statistic of ``STEP_KINDS``, its command in the
    footer."""
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    points, config = step_times(report, plant), report["config"]
    fig, axes = plt.subplots(1, len(STEP_KINDS), figsize=(11, 4.2))
    for ax, (key, title) in zip(axes, STEP_KINDS.items(), strict=True):
        for i, m in enumerate(dict.fromkeys(p["method"] for p in points)):
            ps = [p for p in points if p["method"] == m]
            ax.errorbar(
                [p["horizon"] for p in ps],
                [1e3 * p[key]["mean"] for p in ps],
                yerr=[1e3 * np.nan_to_num(p[key]["se"]) for p in ps],
                capsize=3,
                **{**line_style(i), "marker": "o", "markersize": 5, "markevery": 1},
                label=model_label(m, config),
            )
        horizon_axis(ax, points)
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))  # 10, 100: not 10^1, 10^2
        ax.yaxis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:g}" if f"{v:g}"[0] in "25" else ""))
        ax.set_ylabel("MPC step time [ms]\n(mean ± s.e. over episodes)")
        ax.set_title(title, fontsize=9)
    axes[0].legend(fontsize=7)
    fig.suptitle(
        f"Step time vs planning horizon, {report['scenario']['name']}, {plant} plant: observe + warm start + solves, "
        f"CPU, workers={config.get('workers', '?')}",
        fontsize=10,
    )
    return _save_with_footer(fig, path, f"From `{report['command']}`.")


def planned_trajectory(model: str, seed: int, indices: Sequence[int], path: Path) -> Path:
    """Problems planned (module doc) to ``path``, one panel each: problems ``indices`` of the held-out non-convex
    evaluation stream of root ``seed``, warm-started by ``model`` (a zoo name, bundle folder or .ckpt) at its own
    ``rtg_scale``; each panel's title gives the cost of SCP from the model relative to SCP from REL."""
    from ttompc.evaluation.problems import eval_problem
    from ttompc.evaluation.warmstart import evaluate_problem
    from ttompc.policy import Planner

    planner = Planner.from_pretrained(model, progress=False)
    sc = planner.scenario
    panels = []
    for index in indices:
        ep = eval_problem(sc, seed, index)
        row, trajs = evaluate_problem(sc, ep, {model: planner}, oracle_detours=0)
        costs = {
            "REL (lower bound)": ep.rel_cost,
            "SCP from REL": row["REL_cost"],
            f"SCP from {model}": row[f"{model}_cost"],
        }
        lines = {
            "REL (lower bound)": trajs["REL (lower bound)"],
            f"{model} warm start": trajs[f"{model} rollout"],
            "SCP from REL": trajs["SCP from REL"],
            f"SCP from {model}": trajs[f"SCP from {model}"],
        }
        change = round(100 * (row[f"{model}_cost"] - row["REL_cost"]) / row["REL_cost"], 1) + 0.0  # never -0.0
        panels.append(
            Panel(
                ep.problem,
                lines,
                f"problem {index}: REL inside keep-out zones at {ep.ctg0} steps\n"
                f"J of SCP from {model}: {change:+.1f}% vs SCP from REL",
                {f"SCP from {n}" for n in ("REL", model) if not row[f"{n}_success"]},
                {k: c for k, c in costs.items() if np.isfinite(c)},
            )
        )
    title = (
        f"{sc.name}, held-out non-convex problems of seed {seed}. REL: the convex relaxation without keep-out "
        "zones (a lower bound on J, so it may cross them). J: control cost, lower is better."
    )
    fig = trajectory_figure(sc, panels, title)
    problems = " ".join(str(i) for i in indices)
    return _save_with_footer(
        fig,
        path,
        f"Planned by `python -m ttompc.evaluation.figures ... --model {model} --seed {seed} --problems {problems}` "
        "(`make figures`) with the per-problem step of `ttompc evaluate warmstart`, no oracle detours.",
    )


def make_figures(
    mpc: str | Path,
    warmstart: str | Path,
    out: str | Path,
    *,
    model: str,
    seed: int,
    problems: Sequence[int],
    plant: str,
) -> list[Path]:
    """Every figure of ``FILES`` into ``out`` from the reports at ``mpc`` and ``warmstart`` (both read before
    anything is drawn) and the planned ``problems``; returns their paths."""
    closed, ws = load_report(mpc, "mpc"), load_report(warmstart, "warmstart")
    out = Path(out)
    paths = [planned_trajectory(model, seed, problems, out / FILES[0]), warmstart_figure(ws, out / FILES[1])]
    return [*paths, cost_figure(closed, out / FILES[2], plant), step_time_figure(closed, out / FILES[3], plant)]


def main(argv: Sequence[str] | None = None) -> int:
    """The command line of the module doc; prints the figures written (a ``UserError`` as one line, exit 2)."""
    import matplotlib

    matplotlib.use("Agg")
    p = argparse.ArgumentParser(prog="python -m ttompc.evaluation.figures", description=__doc__.split("\n\n")[0])
    p.add_argument("--mpc", required=True, help="mpc.json of `ttompc evaluate mpc` (several horizons)")
    p.add_argument("--warmstart", required=True, help="warmstart.json of `ttompc evaluate warmstart`")
    p.add_argument("--out", default="docs/figures", help="folder for the figures (default docs/figures)")
    p.add_argument("--model", default="freeflyer-ft-tto-v5", help="the planned trajectory's model")
    p.add_argument("--seed", type=int, default=4242, help="root seed of its evaluation stream (default 4242)")
    p.add_argument(
        "--problems",
        type=int,
        nargs="+",
        default=list(PROBLEMS),
        help=f"their indices in that stream (default {' '.join(map(str, PROBLEMS))})",
    )
    p.add_argument("--plant", default="nominal", choices=("nominal", "perturbed"), help="closed-loop plant")
    args = p.parse_args(argv)
    try:
        paths = make_figures(
            args.mpc,
            args.warmstart,
            args.out,
            model=args.model,
            seed=args.seed,
            problems=args.problems,
            plant=args.plant,
        )
    except UserError as err:
        print(f"{p.prog}: error: {err}", file=sys.stderr)
        return 2
    print("\n".join(str(path) for path in paths))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
