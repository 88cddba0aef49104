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
* ``closed_loop_<plant>.png`` (Fig. 5 and 6) from the ``mpc.json`` of ``ttompc evaluate mpc`` sweeps, one report per
  scenario (``--mpc`` takes several): per plant that every report ran, one column per scenario, the paper's
  normalised cost increment, (J − J_REL)/J_REL and the failure rate, and the largest and mean step time, vs H
  (``ttompc.evaluation.horizon_figures``). The speedup at equal cost of every report is printed below the paths
  (``ttompc.evaluation.equal_cost``), and written to ``--table`` (a markdown file the docs link, ``write_table``).

    python -m ttompc.evaluation.figures --mpc MPC.json [MPC.json ...] --warmstart WARMSTART.json --out docs/figures \
        [--table docs/equal-cost.md]

``make figures`` runs the ``ttompc evaluate`` commands whose reports these are (the Makefile names them) when the
reports are missing, then this. Every report must be complete (``report_files.read_report``).
"""

from __future__ import annotations

import argparse
import sys
import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ttompc.errors import UserError
from ttompc.evaluation.equal_cost import equal_cost, format_equal_cost
from ttompc.evaluation.horizon_figures import horizon_figure, model_label
from ttompc.evaluation.plots import Panel, trajectory_figure
from ttompc.evaluation.report_files import read_report
from ttompc.evaluation.warmstart import ORACLE
from ttompc.model_slots import MODEL_SLOTS

WARMSTART_METHODS = (*MODEL_SLOTS, ORACLE)  # the warm starts Fig. 4 shows, as the warm-start report names them
FILES = ("planned_trajectory.png", "warmstart.png")  # then closed_loop_<plant>.png per plant (``horizon_file``)
# The planned problems of the stream of seed 4242 (the zoo cards'): 0, the first, on which SCP from REL and from
# freeflyer-ft-tto-v5 reach the same optimum (as on 68 of the 100 problems of the warm-start report that `make figures`
# runs); 7, the first on which SCP from the model reaches a cheaper one (21 of 100; 11 the other way).
PROBLEMS = (0, 7)


def load_report(path: str | Path, kind: str) -> dict[str, Any]:
    """The complete report at ``path`` (``report_files.read_report``): ``kind`` "mpc" (``mpc.json``, with
    ``summary`` and ``runs``) or "warmstart" (``warmstart.json``, with ``methods`` and ``thresholds``), the nulls of
    those sections read as nan; raises ``UserError`` for a missing, unreadable or incomplete file, another kind of
    report or a report without its ``command`` (the footer's)."""
    report = read_report(path, kind)
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
    apart), the axes laid out above it and below the figure's title (``suptitle``; ``tight_layout`` leaves it
    out)."""
    lines = textwrap.wrap(text, int(15 * fig.get_figwidth()))
    height = (len(lines) * 7 * 1.35 / 72 + 0.1) / fig.get_figheight()  # inches -> figure fraction
    title = fig._suptitle  # matplotlib's own attribute: there is no public getter
    top = (title.get_fontsize() * 1.35 * (title.get_text().count("\n") + 1) / 72 + 0.05) if title else 0.0
    fig.tight_layout(rect=(0, height, 1, 1 - top / fig.get_figheight()))
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
            oracle = m == ORACLE
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


def horizon_file(plant: str) -> str:
    """The file name of the closed-loop figure of ``plant``."""
    return f"closed_loop_{plant}.png"


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
    mpc: Sequence[str | Path],
    warmstart: str | Path,
    out: str | Path,
    *,
    model: str,
    seed: int,
    problems: Sequence[int],
) -> list[Path]:
    """The figures of ``FILES`` into ``out`` from the warm-start report at ``warmstart`` and the planned
    ``problems``, and ``closed_loop_<plant>.png`` from the closed-loop reports at ``mpc`` (one per scenario) for
    every plant they all ran (every report read before anything is drawn); returns their paths."""
    closed, ws = [load_report(path, "mpc") for path in mpc], load_report(warmstart, "warmstart")
    plants = sorted(set.intersection(*({r["plant"] for r in c["summary"]} for c in closed)))
    if not plants:
        raise UserError("the closed-loop reports share no plant", "pass reports that ran the same plants=")
    out = Path(out)
    paths = [planned_trajectory(model, seed, problems, out / FILES[0]), warmstart_figure(ws, out / FILES[1])]
    for plant in plants:
        fig, footer = horizon_figure(closed, plant)
        paths.append(_save_with_footer(fig, out / horizon_file(plant), footer))
    return paths


def equal_cost_table(mpc: Sequence[str | Path]) -> str:
    """The speedup at equal cost (``equal_cost``) of each closed-loop report at ``mpc``, one table with a scenario
    column."""
    rows = []
    for path in mpc:
        report = load_report(path, "mpc")
        rows += [{"scenario": report["scenario"]["name"], **r} for r in equal_cost(report["runs"])]
    return format_equal_cost(rows)


def write_table(table: str, mpc: Sequence[str | Path], path: str | Path) -> Path:
    """The equal-cost ``table`` (``equal_cost_table``) of the reports at ``mpc`` as the markdown file ``path``
    (the docs link it), headed by the command that wrote it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    command = f"python -m ttompc.evaluation.figures --mpc {' '.join(map(str, mpc))} ... --table {path}"
    path.write_text(
        f"# Speedup at equal cost\n\nWritten by `make figures` (`{command}`) from the closed-loop "
        f"reports; every number comes from them.\n{table}\n",
        encoding="utf-8",
    )
    return path


def main(argv: Sequence[str] | None = None) -> int:
    """The command line of the module doc; prints the figures written (a ``UserError`` as one line, exit 2)."""
    import matplotlib

    matplotlib.use("Agg")
    p = argparse.ArgumentParser(prog="python -m ttompc.evaluation.figures", description=__doc__.split("\n\n")[0])
    p.add_argument("--mpc", required=True, nargs="+", help="mpc.json of `ttompc evaluate mpc` sweeps, one per scenario")
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
    p.add_argument("--table", help="also write the equal-cost table to this markdown file (make figures: docs/)")
    args = p.parse_args(argv)
    try:
        paths = make_figures(
            args.mpc,
            args.warmstart,
            args.out,
            model=args.model,
            seed=args.seed,
            problems=args.problems,
        )
        table = equal_cost_table(args.mpc)
        if args.table:
            paths.append(write_table(table, args.mpc, args.table))
    except UserError as err:
        print(f"{p.prog}: error: {err}", file=sys.stderr)
        return 2
    print("\n".join(str(path) for path in paths))
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
