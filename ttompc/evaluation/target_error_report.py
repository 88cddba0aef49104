"""The report of ``ttompc evaluate target`` (``ttompc.evaluation.target_error``): per (plant, horizon) the errors of
``ERRORS`` by steps to go (``BUCKETS`` of ``ttompc.evaluation.value_error``, and over all steps: mean, median and the
number of steps that have the error), and across the episodes that reached the goal (feasible) the correlation of
each episode's mean error with its closed-loop cost (J − J_REL)/J_REL: Pearson's r and Spearman's ρ with n (nan
below 3 episodes or for a constant error).

Files in the report folder: ``target_error.json`` (config, resolved settings, normalisation, summary, the episodes'
records), ``target_error.md`` (the tables), ``target_error_steps.csv`` (one row per expert step) and, with ``plot``,
``target_error.png`` (the mean of each error by steps to go, one panel per plant).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ttompc.evaluation.metrics import write_csv, write_json
from ttompc.evaluation.value_error import BUCKETS

NORMALISATION = (
    "‖Δ / scale‖₂: each component in units of the scenario's characteristic magnitudes (state_scale for states, "
    "control_scale for controls), then the Euclidean norm"
)
# a step's errors (``target_error.step_errors``, whose module doc defines them) with their labels in the tables
LABELS = {
    "target_raw": "target (raw)",
    "target_blended": "target (blended)",
    "control": "first control (window)",
    "control_raw": "first control (provider)",
}
ERRORS = tuple(LABELS)


def bucket_label(to_go: int) -> str:
    """The ``BUCKETS`` label ("lo-hi") of ``to_go`` steps to go; beyond the last bucket "<last lo>+"."""
    for lo, hi in BUCKETS:
        if lo <= to_go <= hi:
            return f"{lo}-{hi}"
    return f"{BUCKETS[-1][1] + 1}+"


def _stats(values: Sequence[float]) -> dict[str, float]:
    x = np.asarray([v for v in values if v is not None and np.isfinite(v)], dtype=np.float64)
    if not len(x):
        return {"mean": float("nan"), "median": float("nan"), "n": 0}
    return {"mean": float(np.mean(x)), "median": float(np.median(x)), "n": len(x)}


def correlation(x: Sequence[float], y: Sequence[float]) -> dict[str, float]:
    """Pearson's r and Spearman's ρ (ranks, ties averaged) of the pairs where both are finite, with their n; nan
    below 3 pairs or when either side is constant."""
    from scipy.stats import rankdata

    pairs = np.array([(a, b) for a, b in zip(x, y, strict=True) if np.isfinite(a) and np.isfinite(b)], dtype=float)
    out = {"pearson": float("nan"), "spearman": float("nan"), "n": len(pairs)}
    if len(pairs) < 3 or np.ptp(pairs[:, 0]) == 0 or np.ptp(pairs[:, 1]) == 0:
        return out
    out["pearson"] = float(np.corrcoef(pairs[:, 0], pairs[:, 1])[0, 1])
    out["spearman"] = float(np.corrcoef(rankdata(pairs[:, 0]), rankdata(pairs[:, 1]))[0, 1])
    return out


def summarize(records: Sequence[dict[str, Any]], steps: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (plant, horizon), in order of appearance: episodes, feasible, expert fallbacks, the cost increment over the
    feasible episodes, each error by bucket and over all steps, and its correlation with the cost increment."""
    out = []
    for plant, H in dict.fromkeys((r["plant"], r["horizon"]) for r in records):
        recs = [r for r in records if (r["plant"], r["horizon"]) == (plant, H)]
        rows = [s for s in steps if (s["plant"], s["horizon"]) == (plant, H) and not s["expert_fallback"]]
        feasible = [r for r in recs if r["feasible"]]
        buckets: dict[str, dict[str, Any]] = {}
        for label in dict.fromkeys(bucket_label(s["to_go"]) for s in sorted(rows, key=lambda s: -s["to_go"])):
            inside = [s for s in rows if bucket_label(s["to_go"]) == label]
            buckets[label] = {"steps": len(inside), **{k: _stats([s[k] for s in inside]) for k in ERRORS}}
        cost = [r["rel_increment"] for r in feasible]
        out.append(
            {
                "plant": plant,
                "horizon": H,
                "episodes": len(recs),
                "feasible": len(feasible),
                "expert_steps": len(rows),
                "expert_fallbacks": int(sum(r["expert_fallbacks"] for r in recs)),
                "rel_increment": _stats(cost),
                "buckets": buckets,
                "all": {"steps": len(rows), **{k: _stats([s[k] for s in rows]) for k in ERRORS}},
                "correlation": {k: correlation([r[k] for r in feasible], cost) for k in ERRORS},
            }
        )
    return out


def _cell(s: dict[str, float]) -> str:
    return "–" if not s["n"] else f"{s['mean']:.3g} ({s['median']:.3g})"


def _corr(c: dict[str, float]) -> str:
    return f"{c['pearson']:.2f} / {c['spearman']:.2f} (n={c['n']})"


def format_tables(summary: Sequence[dict[str, Any]], method: str) -> str:
    """The markdown tables: the errors by steps to go (mean (median)), then their correlation with the cost."""
    head = " | ".join(LABELS[k] for k in ERRORS)
    lines = [
        f"Errors of {method} against the expert re-solved from the measured state, {NORMALISATION}: mean "
        "(median) over the expert's steps.",
        "",
        f"| plant | H | steps to go | steps | {head} |",
        "|---|---|---|---|" + "---|" * len(ERRORS),
    ]
    for g in summary:
        for label, b in [*g["buckets"].items(), ("all", g["all"])]:
            cells = " | ".join(_cell(b[k]) for k in ERRORS)
            lines.append(f"| {g['plant']} | {g['horizon']} | {label} | {b['steps']} | {cells} |")
    lines += [
        "",
        "Correlation of each episode's mean error with its closed-loop cost (J − J_REL)/J_REL over the "
        "feasible episodes: Pearson / Spearman (n).",
        "",
        f"| plant | H | feasible / episodes | (J − J_REL)/J_REL | {head} |",
        "|---|---|---|---|" + "---|" * len(ERRORS),
    ]
    for g in summary:
        cells = " | ".join(_corr(g["correlation"][k]) for k in ERRORS)
        lines.append(
            f"| {g['plant']} | {g['horizon']} | {g['feasible']} / {g['episodes']} | "
            f"{_cell(g['rel_increment'])} | {cells} |"
        )
    return "\n".join(lines) + "\n"


def plot_target_error(summary: Sequence[dict[str, Any]], path: Path) -> Path:
    """``target_error.png``: the mean of each error by bucket of steps to go, a column per plant, the targets' in
    the first row and the first controls' in the second (a line per error and horizon)."""
    from matplotlib.figure import Figure

    from ttompc.evaluation.plots import save_figure

    plants = list(dict.fromkeys(g["plant"] for g in summary))
    fig = Figure(figsize=(6 * len(plants), 7))
    axes = fig.subplots(2, len(plants), squeeze=False)
    for col, plant in enumerate(plants):
        for row, (what, kinds) in enumerate((("target", ERRORS[:2]), ("first control", ERRORS[2:]))):
            ax = axes[row][col]
            for g in (g for g in summary if g["plant"] == plant):
                labels = list(g["buckets"])
                for k in kinds:
                    ax.plot(
                        labels,
                        [g["buckets"][b][k]["mean"] for b in labels],
                        marker="o",
                        label=f"{LABELS[k]}, H={g['horizon']}",
                    )
            ax.set(title=f"{plant}: {what}", xlabel="steps to go", ylabel="mean error (scaled units)")
            ax.legend(fontsize=7)
    return save_figure(fig, path)


def write_target_report(
    run: dict[str, Any],
    records: list[dict[str, Any]],
    steps: list[dict[str, Any]],
    out: Path,
    plot: bool,
) -> dict[str, Any]:
    """Write the report files into ``out`` (module doc); ``run``: what the report says of its run (``scenario``,
    ``method``, ``config``, ``settings``, ``seconds``). Returns the report with ``table`` and ``out``."""
    summary = summarize(records, steps)
    table = format_tables(summary, run["method"])
    report = {**run, "normalisation": NORMALISATION, "summary": summary, "episodes": records}
    write_json(out / "target_error.json", report)
    (out / "target_error.md").write_text(table)
    write_csv(out / "target_error_steps.csv", steps)
    if plot:
        plot_target_error(summary, out / "target_error.png")
    return {**report, "table": table, "out": str(out)}
