"""Figures of the evaluations (matplotlib Agg, no display): Fig. 3 (warm-start improvement bars), Fig. 4–5
(normalised cost and runtime vs planning horizon) and closed-loop trajectories."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ttompc.scenarios.base import Problem, Scenario


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    _plt().close(fig)
    return path


def plot_horizon(summary: list[dict[str, Any]], out_dir: str | Path) -> list[Path]:
    """Fig. 4 (mean normalised cost increment vs H) and Fig. 5 (mean of the per-episode max step time vs H)."""
    plt = _plt()
    methods = sorted({r["method"] for r in summary})
    paths = []
    for field, ylabel, name in (
        ("norm_cost_increment", "normalised cost increment", "horizon_cost.png"),
        ("max_step_time", "max MPC step time [s]", "horizon_runtime.png"),
    ):
        fig, ax = plt.subplots(figsize=(5, 3.5))
        for m in methods:
            rs = sorted((r for r in summary if r["method"] == m), key=lambda r: r["horizon"])
            ax.plot([r["horizon"] for r in rs], [r[field] for r in rs], "o-", label=m)
        ax.set_xlabel("planning horizon H")
        ax.set_ylabel(ylabel)
        if field == "max_step_time":
            ax.set_yscale("log")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        paths.append(_save(fig, Path(out_dir) / name))
    return paths


def plot_warmstart(rows: list[dict[str, Any]], methods: Sequence[str], out_dir: str | Path) -> Path:
    """Fig. 3: % improvement over the REL warm start in suboptimality (top) and SCP iterations (bottom), per
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


def trajectory_figure(
    scenario: Scenario, problem: Problem, trajectories: dict[str, np.ndarray], title: str = ""
) -> Any:
    """The scenario's own drawing (keep-out zones, start, goal) of executed trajectories (label -> states)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5, 4))
    scenario.plot(ax, problem, trajectories)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return fig
