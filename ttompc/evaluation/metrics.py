"""Metrics of the evaluations (paper §V-B, §V-C; protocol: ``docs/evaluation.md``) and their JSON/CSV reports.

* absolute: (J − J_REL)/J_REL per run, J_REL the open-loop REL cost (a lower bound of the full problem); means over
  feasible runs only, with standard error and bootstrap interval (``ttompc.evaluation.stats.interval``); infeasible runs
  are counted apart.
* the paper's normalised cost increment (Fig. 5): (J − J_REL)/(maxcost − J_REL) per feasible run, maxcost the worst
  feasible cost of its problem over every method and horizon (``normalized_cost``); runs that miss the goal or
  violate a constraint are counted apart.
* share of the reachable gain: (mean J_base − mean J_m)/(mean J_base − mean J_oracle) over problems solved by base,
  model and oracle — 0 = no better than the baseline (SCP from REL open loop, REL-MPC closed loop), 1 = as good as
  the oracle — with a paired bootstrap interval; undefined (nan, null in JSON) when the reachable gain
  mean(J_base − J_oracle) is within noise (``gain_share``).
* warm-start improvement (Fig. 4): for each threshold c of the non-convexity factor (ctg0 / max ctg0), over problems
  with factor ≥ c solved by every method: 100·(1 − mean(J_m − J_REL)/mean(J_SCP(REL) − J_REL)) for the suboptimality
  and 100·(1 − mean(iter_m)/mean(iter_SCP(REL))) for the SCP iterations.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ttompc.evaluation.stats import BOOTSTRAP_SAMPLES, format_interval, interval


def normalized_cost(records: list[dict[str, Any]], *, seed: int = 0) -> list[dict[str, Any]]:
    """The paper's normalised cost increment (§V-C, Fig. 5), (J − LB)/(maxcost − LB), of closed-loop ``records``
    (keys problem, method, horizon, cost, rel_cost, feasible) of one plant, per problem: LB is the problem's REL cost
    J_REL (the lower bound) and maxcost the largest cost of a feasible run of that problem over every method and
    horizon of ``records`` ("the worst performance observed across all planning horizons": 1). Runs that miss the
    goal or violate a constraint have no cost and are counted apart (their rate is the report's ``feasible``/``runs``);
    every feasible run of a problem with a feasible run above LB counts. Rows (method, horizon, ``paper_norm``: the
    ``interval`` over those runs), methods in first-seen order, horizons ascending."""
    worst: dict[Any, float] = {}
    for r in records:
        if r["feasible"]:
            worst[r["problem"]] = max(worst.get(r["problem"], -math.inf), float(r["cost"]))
    values: dict[tuple[str, int], list[float]] = {}
    for r in records:
        span = worst.get(r["problem"], -math.inf) - r["rel_cost"]
        run = values.setdefault((r["method"], r["horizon"]), [])  # a row for every (method, horizon) that ran
        if r["feasible"] and span > 0:
            run.append((r["cost"] - r["rel_cost"]) / span)
    methods = list(dict.fromkeys(r["method"] for r in records))
    horizons = sorted({r["horizon"] for r in records})
    return [
        {"method": m, "horizon": h, "paper_norm": interval(values[(m, h)], seed=seed)}
        for m in methods
        for h in horizons
        if (m, h) in values
    ]


# The smallest reachable gain that counts, relative to the baseline's mean cost: below 0.01% the costs agree to more
# digits than any table shows, and the share is a ratio of rounding noise.
GAIN_FLOOR = 1e-4
GAIN_Z = 2.0  # the reachable gain must exceed GAIN_Z paired standard errors (about 95% one-sided) to be a gain


def gain_share(base: np.ndarray, model: np.ndarray, ceiling: np.ndarray, *, seed: int = 0) -> dict[str, Any]:
    """Share of the reachable gain (mean(base) − mean(model))/(mean(base) − mean(ceiling)) over paired per-problem
    costs (rows with a nan anywhere are dropped), with a paired bootstrap 95% interval and, as s.e., half the width
    of the central 68% of the bootstrap distribution (robust to the ratio's heavy tails).

    The share is undefined (nan: null in JSON, ``undefined`` in tables with the reason in ``undefined``) when its
    denominator, the reachable gain G = mean(base − ceiling), is within noise: G ≤ ``GAIN_Z`` paired standard errors
    of base − ceiling, or G ≤ ``GAIN_FLOOR``·|mean(base)|, or fewer than two problems (no standard error); dividing
    by such a G turned three methods at the same cost into a share of 24 ± 50%. ``reachable_gain`` holds G's
    interval either way. Bootstrap resamples whose gain is within noise are left out of the share's interval."""
    rows = np.column_stack([base, model, ceiling]).astype(np.float64)
    rows = rows[np.all(np.isfinite(rows), axis=1)]
    n = len(rows)
    out: dict[str, Any] = {"mean": float("nan"), "se": float("nan"), "lo": float("nan"), "hi": float("nan"), "n": n}
    out["reachable_gain"] = interval(rows[:, 0] - rows[:, 2], seed=seed)
    if n < 2:
        out["undefined"] = "no problem solved by all three" if n == 0 else "one problem: no standard error"
        return out
    shares = _shares(rows[None])
    if not np.isfinite(shares[0]):
        out["undefined"] = "reachable gain within noise"
        return out
    out["mean"], out["undefined"] = float(shares[0]), None
    idx = np.random.default_rng(seed).integers(0, n, size=(BOOTSTRAP_SAMPLES, n))
    boot = _shares(rows[idx])
    boot = boot[np.isfinite(boot)]
    if len(boot) > 1:
        q16, q84, lo, hi = np.quantile(boot, [0.16, 0.84, 0.025, 0.975])
        out["se"], out["lo"], out["hi"] = float((q84 - q16) / 2), float(lo), float(hi)
    return out


def _shares(samples: np.ndarray) -> np.ndarray:
    """The gain share of each sample (S, n, 3) of paired (base, model, ceiling) rows; nan where the reachable gain
    is within noise (see ``gain_share``)."""
    b, m, _ = samples.mean(axis=1).T
    d = samples[..., 0] - samples[..., 2]
    gain = d.mean(axis=1)
    se = d.std(axis=1, ddof=1) / np.sqrt(samples.shape[1])
    clear = (gain > GAIN_Z * se) & (gain > GAIN_FLOOR * np.abs(b))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(clear, (b - m) / gain, np.nan)


def format_gain_share(share: dict[str, Any]) -> str:
    """'mean ± se [lo, hi]' in % of a ``gain_share`` for tables, or 'undefined (why)' when it has no value."""
    if share.get("undefined"):
        return f"undefined ({share['undefined']})"
    return format_interval(share, 100)


def _mean(values: Sequence[float]) -> float:
    vals = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    return float(np.mean(vals)) if vals else float("nan")


def aggregate(records: list[dict[str, Any]], keys: Sequence[str], fields: Sequence[str]) -> list[dict[str, Any]]:
    """Mean of ``fields`` per group of ``keys`` (plus ``count``)."""
    groups: dict[tuple, list[dict[str, Any]]] = defaultdict(list)
    for r in records:
        groups[tuple(r[k] for k in keys)].append(r)
    out = []
    for key in sorted(groups, key=lambda k: tuple(str(x) if isinstance(x, str) else x for x in k)):
        rs = groups[key]
        row = dict(zip(keys, key, strict=True))
        row["count"] = len(rs)
        for f in fields:
            row[f] = _mean([r[f] for r in rs])
        out.append(row)
    return out


def improvement_by_threshold(
    problems: list[dict[str, Any]], methods: Sequence[str], baseline: str, thresholds: Sequence[float]
) -> list[dict[str, Any]]:
    """Fig. 4 rows: per threshold c and method, % improvement of suboptimality and iterations over ``baseline``.

    ``problems`` rows hold ``nonconvexity`` (in [0, 1]), ``rel_cost`` and ``<method>_cost``/``<method>_iterations``/
    ``<method>_success`` for the baseline and every method; only problems solved by all of them count."""
    names = [baseline, *methods]
    ok = [p for p in problems if all(p[f"{m}_success"] for m in names)]
    rows = []
    for c in thresholds:
        sel = [p for p in ok if p["nonconvexity"] >= c - 1e-12]
        row: dict[str, Any] = {"threshold": float(c), "count": len(sel)}
        if sel:
            base_gap = np.mean([p[f"{baseline}_cost"] - p["rel_cost"] for p in sel])
            base_it = np.mean([p[f"{baseline}_iterations"] for p in sel])
            for m in methods:
                gap = np.mean([p[f"{m}_cost"] - p["rel_cost"] for p in sel])
                it = np.mean([p[f"{m}_iterations"] for p in sel])
                row[f"{m}_subopt_improvement"] = float(100 * (1 - gap / base_gap)) if base_gap > 0 else float("nan")
                row[f"{m}_iterations_improvement"] = float(100 * (1 - it / base_it)) if base_it > 0 else float("nan")
        rows.append(row)
    return rows


def write_csv(path: str | Path, rows: list[dict[str, Any]]) -> Path:
    """Rows with possibly different keys -> one CSV (union of columns, first-seen order)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    cols: list[str] = []
    for r in rows:
        cols += [k for k in r if k not in cols]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols)
        w.writeheader()
        w.writerows(rows)
    return path


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        return None if not math.isfinite(float(x)) else float(x)
    if isinstance(x, (np.integer, np.bool_)):
        return x.item()
    return x


def write_json(path: str | Path, obj: Any) -> Path:
    """JSON with numpy values converted and non-finite floats as null (strict JSON), written whole or not at all: to
    a temporary sibling, then renamed over ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(json.dumps(_jsonable(obj), indent=2) + "\n")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
