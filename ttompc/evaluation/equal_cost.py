"""The speedup at equal cost: the paper's "REL-MPC needs H = 30 to match FT-TTO-MPC at H = 10, about 7× the runtime
for the same performance" (§V-C), read off a closed-loop sweep (``ttompc evaluate mpc`` over several horizons).

Per plant, two questions (``equal_cost``), each answered by the smallest horizon that matches:

* ``rel_catches_up``: the smallest H at which REL-MPC's cost is not worse than the learned method's at its short
  horizon (``LEARNED``@``LEARNED_HORIZON``, R-FT-TTO-MPC@10);
* ``learned_catches_up``: the smallest H at which the learned method's cost is not worse than REL-MPC@
  ``BASELINE_HORIZON`` (30).

"Not worse" is paired: over the problems both runs reached feasibly (``stats.paired``), the mean difference in
(J − J_REL)/J_REL, moving − fixed, is at most one standard error (so at least two such problems). Beside the match,
the step-time ratio REL-MPC / learned method there, of the mean step time and of the largest (each episode's
largest step, averaged over the episodes: Fig. 6's measure), over the problems both ran. No H matches, or a method
or horizon that did not run: ``horizon`` None and ``why`` saying which. A model method's name may carry its rtg mode
(``R-FT-TTO-MPC[rtg=value]``): methods are matched by the name before the bracket.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Sequence
from typing import Any

from ttompc.evaluation.stats import Outcome, format_interval, paired
from ttompc.mpc.methods import BASELINE, base_method, model_method

LEARNED, LEARNED_HORIZON, BASELINE_HORIZON = model_method("FT-TTO", robust=True).name, 10, 30


def _runs(records: Sequence[dict[str, Any]], plant: str, method: str, horizon: int) -> dict[int, dict[str, Any]]:
    return {
        r["problem"]: r
        for r in records
        if r["plant"] == plant and base_method(r["method"]) == method and r["horizon"] == horizon
    }


def _outcomes(runs: dict[int, dict[str, Any]], step: str) -> dict[Hashable, Outcome]:
    return {p: Outcome(bool(r["feasible"]), float(r["rel_increment"]), float(r[step])) for p, r in runs.items()}


def match(
    records: Sequence[dict[str, Any]], plant: str, moving: str, fixed: str, fixed_horizon: int, *, seed: int = 0
) -> dict[str, Any]:
    """The smallest horizon at which ``moving``'s cost is not worse than ``fixed``@``fixed_horizon`` on ``plant``
    (module doc): a row with ``horizon`` (None: no match, ``why``), ``paired`` (moving − fixed, points), ``goals``
    (moving, fixed, problems both ran) and ``mean_ratio`` / ``largest_ratio`` (REL-MPC's step time / the other's)."""
    row: dict[str, Any] = {"plant": plant, "moving": moving, "fixed": f"{fixed}@{fixed_horizon}", "horizon": None}
    ref = _runs(records, plant, fixed, fixed_horizon)
    horizons = sorted({r["horizon"] for r in records if r["plant"] == plant and base_method(r["method"]) == moving})
    if not ref or not horizons:
        row["why"] = f"{fixed}@{fixed_horizon} did not run" if not ref else f"{moving} did not run"
        return row
    for H in horizons:
        runs = _runs(records, plant, moving, H)
        pair = paired(_outcomes(ref, "mean_step_time"), _outcomes(runs, "mean_step_time"), scale=100, seed=seed)
        d = pair["paired"]
        if not (d["n"] >= 2 and d["mean"] <= d["se"]):
            continue
        largest = paired(_outcomes(ref, "max_step_time"), _outcomes(runs, "max_step_time"), seed=seed)
        goals = (pair["other_goals"], pair["base_goals"], pair["problems"])
        rel_moving = moving == BASELINE
        row.update(
            horizon=H,
            paired=d,
            goals=goals,
            mean_ratio=_ratio(pair, rel_moving),
            largest_ratio=_ratio(largest, rel_moving),
        )
        return row
    row["why"] = f"H = {', '.join(map(str, horizons))} tried"
    return row


def _ratio(pair: dict[str, Any], rel_moving: bool) -> float:
    """REL-MPC's step time over the other method's in a ``paired`` result (REL-MPC the moving method or the base)."""
    rel, other = pair["other_step_time"], pair["base_step_time"]
    if not rel_moving:
        rel, other = other, rel
    return rel / other if other > 0 else math.nan


def equal_cost(records: Sequence[dict[str, Any]], *, seed: int = 0) -> list[dict[str, Any]]:
    """Both questions of the module doc on every plant of ``records`` (plants sorted): REL-MPC against
    ``LEARNED``@``LEARNED_HORIZON``, then ``LEARNED`` against REL-MPC@``BASELINE_HORIZON``."""
    rows = []
    for plant in sorted({r["plant"] for r in records}):
        rows.append(match(records, plant, BASELINE, LEARNED, LEARNED_HORIZON, seed=seed))
        rows.append(match(records, plant, LEARNED, BASELINE, BASELINE_HORIZON, seed=seed))
    return rows


def format_equal_cost(rows: Sequence[dict[str, Any]]) -> str:
    """A markdown table of ``equal_cost`` rows (with a ``scenario`` column when the rows carry one)."""
    if not rows:
        return ""
    scen = any("scenario" in r for r in rows)
    lines = [
        "\n### Speedup at equal cost: the smallest H at which a method is not worse than the other at a fixed H\n",
        f"|{' scenario |' if scen else ''} plant | method | not worse than | at H | paired Δ, points (n) | goals "
        f"(method, other / both ran) | {BASELINE} / {LEARNED} step time: mean, largest |",
        f"|{'---|' if scen else ''}---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lead = f"| {r['scenario']} " if scen else ""
        if r["horizon"] is None:
            lines.append(
                f"{lead}| {r['plant']} | {r['moving']} | {r['fixed']} | no H matches ({r['why']}) | – | – | – |"
            )
            continue
        d, (mine, other, both) = r["paired"], r["goals"]
        lines.append(
            f"{lead}| {r['plant']} | {r['moving']} | {r['fixed']} | {r['horizon']} | {format_interval(d)} ({d['n']}) "
            f"| {mine}, {other} / {both} | {r['mean_ratio']:.2g}×, {r['largest_ratio']:.2g}× |"
        )
    lines.append(
        "\nNot worse: the mean paired difference in (J − J_REL)/J_REL (method − other, over the n problems both "
        "reached feasibly) is at most one standard error. Step times over the problems both ran; largest: each "
        "episode's largest step, averaged over the episodes."
    )
    return "\n".join(lines)
