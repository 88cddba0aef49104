"""Metrics of the evaluations (paper §V-B, §V-C; fact sheet §5.4, §5.5) and their JSON/CSV reports.

* normalised cost increment (Fig. 4): per problem, (J − LB)/(J_max − LB) with LB = J_REL (open-loop REL cost, a lower
  bound of the full problem) and J_max the largest cost of that problem over all methods and horizons of the study;
  0 = the lower bound, 1 = the worst run observed.
* warm-start improvement (Fig. 3): for each threshold c of the non-convexity factor (ctg0 / max ctg0), over problems
  with factor ≥ c solved by every method: 100·(1 − mean(J_m − J_REL)/mean(J_SCP(REL) − J_REL)) for the suboptimality
  and 100·(1 − mean(iter_m)/mean(iter_SCP(REL))) for the SCP iterations.
"""

from __future__ import annotations

import csv
import json
import math
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np


def normalized_cost_increment(records: list[dict[str, Any]]) -> None:
    """Add ``norm_cost_increment`` to each record (keys problem, cost, rel_cost) in place, per problem over all
    its records (methods × horizons)."""
    by_problem: dict[Any, list[dict[str, Any]]] = defaultdict(list)
    for r in records:
        by_problem[r["problem"]].append(r)
    for rs in by_problem.values():
        lb = rs[0]["rel_cost"]
        worst = max(r["cost"] for r in rs)
        span = worst - lb
        for r in rs:
            r["norm_cost_increment"] = float((r["cost"] - lb) / span) if span > 0 else 0.0


def _mean(values: Sequence[float]) -> float:
    vals = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    return float(np.mean(vals)) if vals else float("nan")


def aggregate(records: list[dict[str, Any]], keys: Sequence[str], fields: Sequence[str]) -> list[dict[str, Any]]:
    """Mean of ``fields`` per group of ``keys`` (plus ``count`` and ``feasible_rate`` when records have it)."""
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
        if "feasible" in rs[0]:
            row["feasible_rate"] = _mean([float(r["feasible"]) for r in rs])
        out.append(row)
    return out


def improvement_by_threshold(
    problems: list[dict[str, Any]], methods: Sequence[str], baseline: str, thresholds: Sequence[float]
) -> list[dict[str, Any]]:
    """Fig. 3 rows: per threshold c and method, % improvement of suboptimality and iterations over ``baseline``.

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
    """JSON with numpy values converted and non-finite floats as null (strict JSON)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(_jsonable(obj), indent=2) + "\n")
    return path
