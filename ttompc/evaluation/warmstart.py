"""Open-loop warm-start evaluation (paper §V-B, Fig. 3; fact sheet §5.4).

For seeded held-out problems: REL (timed) → SCP from the REL warm start, versus a transformer rollout conditioned on
rtg_0 = −J_REL, ctg_0 = 0 → SCP from that warm start (TTO, and FT-TTO when a second model is given). Per problem:
cost, suboptimality (J − J_REL)/J_REL, SCP iterations, runtime (warm start + SCP), success. Reported per method,
per non-convexity bin (ctg0 / max ctg0 in [c, c+0.1)) and as Fig. 3's % improvement over the REL warm start for
problems with non-convexity ≥ c (problems solved by every method).

Our SCP returns its best feasible iterate, so "cost" is the reference's min(J_vect) and the returned trajectory at
once; iteration counts are the number of convex subproblems solved (the reference's drone/freeflyer counts are
one lower).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ttompc.evaluation.common import eval_problem, pool_map, scenario_module, worker_setup
from ttompc.evaluation.metrics import aggregate, improvement_by_threshold, write_csv, write_json
from ttompc.scenarios import get_scenario
from ttompc.solvers.scp import solve_scp

BASELINE = "REL"


@dataclass
class WarmStartConfig:
    scenario: str
    out: str
    checkpoint: str | None = None
    ft_checkpoint: str | None = None
    problems: int = 200
    seed: int = 0
    workers: int = 1
    thresholds: list[float] = field(default_factory=lambda: [round(0.1 * i, 1) for i in range(10)])
    backend: str = "auto"
    device: str = "cpu"


_W: dict[str, Any] = {}


def _init(module: str, cfg: dict[str, Any]) -> None:
    from ttompc.policy import Planner

    worker_setup(module)
    _W["cfg"] = WarmStartConfig(**cfg)
    _W["scenario"] = scenario = get_scenario(cfg["scenario"])
    _W["models"] = {
        name: Planner.from_pretrained(cfg[key], scenario, device=cfg["device"])
        for name, key in (("TTO", "checkpoint"), ("FT-TTO", "ft_checkpoint"))
        if cfg[key]
    }


def _record(row: dict[str, Any], name: str, res: Any, ws_time: float, rel_cost: float) -> None:
    row[f"{name}_success"] = bool(res.success)
    row[f"{name}_cost"] = float(res.cost) if res.success else float("nan")
    row[f"{name}_suboptimality"] = float((res.cost - rel_cost) / rel_cost) if res.success else float("nan")
    row[f"{name}_iterations"] = int(res.iterations)
    row[f"{name}_warmstart_time"] = ws_time
    row[f"{name}_scp_time"] = float(res.solve_time)
    row[f"{name}_time"] = ws_time + float(res.solve_time)


def _run_problem(index: int) -> dict[str, Any]:
    cfg: WarmStartConfig = _W["cfg"]
    sc = _W["scenario"]
    ep = eval_problem(sc, cfg.seed, index, backend=cfg.backend)
    p, rel = ep.problem, ep.rel
    row: dict[str, Any] = {"problem": index, "seed": ep.seed, "ctg0": ep.ctg0, "rel_cost": rel.cost}
    _record(row, BASELINE, solve_scp(sc, p, rel.X, rel.U, backend=cfg.backend), ep.rel_time, rel.cost)
    for name, planner in _W["models"].items():
        t0 = time.perf_counter()
        X, U = planner.warm_start([p], rtg0=-rel.cost, ctg0=0.0)
        ws_time = time.perf_counter() - t0
        _record(row, name, solve_scp(sc, p, X[0], U[0], backend=cfg.backend), ws_time, rel.cost)
    return row


def run_warmstart(cfg: WarmStartConfig) -> dict[str, Any]:
    """Run the evaluation; writes ``warmstart.json``, ``warmstart_problems.csv``, ``warmstart_thresholds.csv``,
    ``warmstart_bins.csv`` and ``warmstart_improvement.png`` into ``cfg.out``."""
    from ttompc.evaluation.plots import plot_warmstart

    sc = get_scenario(cfg.scenario)
    t0 = time.perf_counter()
    rows = list(
        pool_map(_run_problem, range(cfg.problems), cfg.workers, _init, (scenario_module(sc.name), asdict(cfg)))
    )
    methods = [m for m, key in (("TTO", cfg.checkpoint), ("FT-TTO", cfg.ft_checkpoint)) if key]
    cmax = max((r["ctg0"] for r in rows), default=0)
    for r in rows:
        r["nonconvexity"] = r["ctg0"] / cmax if cmax > 0 else 0.0
        r["bin"] = min(float(np.floor(r["nonconvexity"] * 10) / 10), 0.9)
    per_method = []
    for m in [BASELINE, *methods]:
        ok = [r for r in rows if r[f"{m}_success"]]
        per_method.append(
            {
                "method": m,
                "failures": len(rows) - len(ok),
                **{
                    f: float(np.mean([r[f"{m}_{f}"] for r in ok])) if ok else float("nan")
                    for f in ("cost", "suboptimality", "iterations", "time", "warmstart_time", "scp_time")
                },
            }
        )
    fields = [f"{m}_{f}" for m in [BASELINE, *methods] for f in ("suboptimality", "iterations", "time")]
    bins = aggregate(rows, ("bin",), fields)
    thresholds = improvement_by_threshold(rows, methods, BASELINE, cfg.thresholds)
    out = Path(cfg.out)
    report = {
        "config": asdict(cfg),
        "scenario": {"name": sc.name, "version": sc.version, "n_steps": sc.n_steps},
        "wall_time_s": time.perf_counter() - t0,
        "max_ctg0": cmax,
        "methods": per_method,
        "bins": bins,
        "thresholds": thresholds,
        "problems": rows,
    }
    write_json(out / "warmstart.json", report)
    write_csv(out / "warmstart_problems.csv", rows)
    write_csv(out / "warmstart_thresholds.csv", thresholds)
    write_csv(out / "warmstart_bins.csv", bins)
    report["plots"] = [str(plot_warmstart(thresholds, methods, out))]
    return report
