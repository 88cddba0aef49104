"""Figures of the evaluations (matplotlib Agg, no display), after the paper's: Fig. 4 (warm-start improvement bars),
Fig. 5–6 (cost and runtime vs planning horizon) and trajectories."""

from __future__ import annotations

import textwrap
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from ttompc.scenarios.base import Problem, Scenario


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: str | Path, footer: str = "") -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if footer:
        fig.text(0.01, 0.005, footer, fontsize=7)
    fig.tight_layout(rect=(0, 0.02 if footer else 0, 1, 1))
    fig.savefig(path, dpi=110)
    _plt().close(fig)
    return path


Row = TypeVar("Row")


def row_figure(
    rows: Sequence[Row],
    draw: Callable[[Row, Sequence[Any]], None],
    out: Path,
    *,
    size: tuple[float, float],
    panels: int = 3,
    footer: str = "",
) -> Path:
    """A figure of one row of ``panels`` axes per item of ``rows`` (e.g. a learning curve, one run or curve file a
    row), ``draw(row, axes)`` filling each row; ``size``: (width, height of one row) in inches; ``footer``: one line
    of small text at the bottom (e.g. the command that drew it). Written to ``out`` (folders created, 110 dpi) and
    closed; returns ``out``."""
    fig, grid = _plt().subplots(len(rows), panels, figsize=(size[0], size[1] * len(rows)), squeeze=False)
    for row, axes in zip(rows, grid, strict=True):
        draw(row, axes)
    return _save(fig, out, footer)


def plot_horizon(summary: list[dict[str, Any]], out_dir: str | Path) -> list[Path]:
    """``mpc_cost.png`` (``horizon_cost_figure``) and ``mpc_runtime.png`` (Fig. 6 analogue: the largest step time
    of each method vs H)."""
    plt = _plt()
    paths = [_save(horizon_cost_figure(summary), Path(out_dir) / "mpc_cost.png")]
    plants = sorted({r["plant"] for r in summary})
    methods = list(dict.fromkeys(r["method"] for r in summary))
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for i, m in enumerate(methods):
        rs = sorted((r for r in summary if r["method"] == m and r["plant"] == plants[0]), key=lambda r: r["horizon"])
        ax.plot([r["horizon"] for r in rs], [r["max_step_time"] for r in rs], **line_style(i), label=m)
    horizon_axis(ax, summary)
    ax.set_ylabel("max MPC step time [s]")
    ax.set_yscale("log")
    ax.legend(fontsize=7)
    paths.append(_save(fig, Path(out_dir) / "mpc_runtime.png"))
    return paths


def horizon_cost_figure(summary: list[dict[str, Any]]) -> Any:
    """Fig. 5 analogue: mean (J − J_REL)/J_REL over feasible runs ± s.e. vs H, one panel per plant
    (``horizon_cost_panel``)."""
    plt = _plt()
    plants = sorted({r["plant"] for r in summary})
    fig, axes = plt.subplots(1, len(plants), figsize=(5 * len(plants), 3.8), squeeze=False)
    for ax, plant in zip(axes[0], plants, strict=True):
        horizon_cost_panel(ax, [r for r in summary if r["plant"] == plant])
        ax.set_title(f"{plant} plant", fontsize=9)
    return fig


def horizon_cost_panel(
    ax: Any, rows: list[dict[str, Any]], labels: dict[str, str] | None = None, styles: dict[str, int] | None = None
) -> None:
    """Mean (J − J_REL)/J_REL over feasible runs ± s.e. vs H of the summary ``rows`` of one plant on ``ax``, one line
    per method (legend: ``labels[method]``, default the method; style: ``line_style(styles[method])``, default the
    method's place in ``rows``). No method is dropped where runs were infeasible: a hollow marker is the mean of the
    feasible runs when some were infeasible, a hollow triangle at the top edge marks a horizon with no feasible run,
    both annotated feasible/runs."""
    from matplotlib.lines import Line2D

    labels = labels or {}
    for i, m in enumerate(dict.fromkeys(r["method"] for r in rows)):
        rs = sorted((r for r in rows if r["method"] == m), key=lambda r: r["horizon"])
        style = {**line_style((styles or {}).get(m, i)), "marker": "o", "markersize": 5}
        style["markevery"] = [r["feasible"] == r["runs"] for r in rs]  # filled: every run feasible
        line = ax.errorbar(
            [r["horizon"] for r in rs],
            [100 * r["rel_increment"]["mean"] if r["feasible"] else np.nan for r in rs],
            yerr=[100 * np.nan_to_num(r["rel_increment"]["se"]) for r in rs],
            capsize=3,
            **style,
            label=labels.get(m, m),
        )[0]
        color = line.get_color()
        for r in rs:
            if r["feasible"] == r["runs"]:
                continue
            count = f"{r['feasible']}/{r['runs']}"
            if r["feasible"]:
                y, transform, marker = 100 * r["rel_increment"]["mean"], ax.transData, "o"
            else:  # no cost to show: a marker at the top edge of the panel
                y, transform, marker = 0.97, ax.get_xaxis_transform(), "^"
            ax.plot(
                [r["horizon"]],
                [y],
                marker,
                transform=transform,
                mfc="none",
                mec=color,
                mew=1.5,
                ms=8,
                clip_on=False,
                zorder=10,
                label=f"_{m} {count} feasible",
            )
            ax.annotate(
                count,
                (r["horizon"], y),
                xycoords=transform,
                xytext=(6, 3),
                textcoords="offset points",
                fontsize=6,
                color=color,
            )
    horizon_axis(ax, rows)
    ax.set_ylabel("(J − J_REL)/J_REL of feasible runs [%]")
    keys = [
        Line2D([], [], ls="", marker="o", mfc="none", mec="0.4", label="some runs infeasible (feasible/runs)"),
        Line2D([], [], ls="", marker="^", mfc="none", mec="0.4", label="no feasible run"),
    ]
    ax.legend(handles=[*ax.get_legend_handles_labels()[0], *keys], fontsize=7)


def horizon_axis(ax: Any, summary: list[dict[str, Any]]) -> None:
    """Ticks at the evaluated horizons only (integers, never 12.5)."""
    ax.set_xticks(sorted({int(r["horizon"]) for r in summary}))
    ax.set_xlabel("planning horizon H")
    ax.grid(alpha=0.3)


def plot_warmstart(rows: list[dict[str, Any]], methods: Sequence[str], out_dir: str | Path) -> Path:
    """Fig. 4: % improvement over the REL warm start in suboptimality (top) and SCP iterations (bottom), per
    non-convexity threshold."""
    plt = _plt()
    fig, axes = plt.subplots(2, 1, figsize=(6, 5), sharex=True)
    x = np.arange(len(rows))
    width = 0.8 / max(len(methods), 1)
    for ax, key, label in (
        (axes[0], "subopt_improvement", "suboptimality improvement [%]"),
        (axes[1], "iterations_improvement", "iterations improvement [%]"),
    ):
        for j, m in enumerate(methods):
            vals = [r.get(f"{m}_{key}", np.nan) for r in rows]
            ax.bar(x + (j - (len(methods) - 1) / 2) * width, vals, width, label=m)
        ax.axhline(0, color="k", lw=0.8)
        ax.set_ylabel(label)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=8)
    axes[1].set_xticks(x, [f"{r['threshold']:.1f}" for r in rows])
    axes[1].set_xlabel("non-convexity factor ≥")
    return _save(fig, Path(out_dir) / "warmstart_improvement.png")


_LINESTYLES = ("-", "--", "-.", ":")


def line_style(i: int) -> dict[str, Any]:
    """The i-th of a set of distinguishable line styles: colour, dash pattern and width all change, and earlier
    lines are wider and drawn below later ones, so two identical trajectories both stay visible."""
    return {
        "color": f"C{i % 10}",
        "linestyle": _LINESTYLES[i % len(_LINESTYLES)],
        "linewidth": max(5.0 - 0.8 * i, 1.0),
        "zorder": 2 + i,
        "marker": "o" if i % 2 else "",
        "markevery": 10,
        "markersize": 3,
    }


@dataclass
class Panel:
    """One problem of a trajectory figure: label -> states (the optimisation representation), the labels whose run
    was infeasible (drawn with an x at the end and marked in the legend), each label's cost where it has one (shown
    in the legend) and a title (e.g. the problem seed)."""

    problem: Problem
    trajectories: dict[str, np.ndarray]
    title: str = ""
    infeasible: set[str] = field(default_factory=set)
    costs: dict[str, float] = field(default_factory=dict)


def trajectory_figure(scenario: Scenario, panels: Sequence[Panel], title: str = "", rows: int = 1) -> Any:
    """The scenario's own drawing (keep-out zones, start, goal) of each panel's trajectories on a grid of ``rows``
    rows, every label in its own style (same label, same style in every panel)."""
    plt = _plt()
    cols = -(-len(panels) // rows)
    fig, axes = plt.subplots(rows, cols, figsize=(6 * cols, 4.8 * rows), squeeze=False)
    labels = list(dict.fromkeys(k for p in panels for k in p.trajectories))
    for ax in axes.flat[len(panels) :]:
        ax.set_visible(False)
    for ax, panel in zip(axes.flat, panels, strict=False):
        scenario.plot(ax, panel.problem, panel.trajectories)
        for line in ax.get_lines():
            label = line.get_label()
            if label in labels:
                line.set(**line_style(labels.index(label)))
                if label in panel.costs:
                    line.set_label(f"{line.get_label()}: J = {panel.costs[label]:.4g}")
                if label in panel.infeasible:
                    line.set_label(f"{line.get_label()} (INFEASIBLE)")
                    x, y = line.get_data()
                    ax.plot(x[-1:], y[-1:], "x", color=line.get_color(), markersize=12, mew=3, zorder=20)
        ax.legend(loc="best", fontsize=7, framealpha=0.7)
        ax.set_title(panel.title, fontsize=9)
    if title:  # wrapped to the figure's width (about 11 characters per inch at this size)
        width = int(11 * fig.get_figwidth())
        fig.suptitle("\n".join(textwrap.fill(line, width) for line in title.splitlines()), fontsize=10)
    fig.tight_layout()
    return fig


def save_figure(fig: Any, path: str | Path) -> Path:
    """Write a figure as PNG (folders created) and close it."""
    return _save(fig, path)
