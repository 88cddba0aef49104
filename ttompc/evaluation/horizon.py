"""Closed-loop planning-horizon study (paper §V-C, Fig. 4–5; fact sheet §5.5).

For seeded held-out problems whose REL solution violates a keep-out zone (ctg0 > 0, like the paper), run REL-MPC,
DIST-MPC, TTO-MPC (and FT-TTO-MPC when a fine-tuned model is given) for every planning horizon H, all in soft mode
with the exact dynamics. Reports per (problem, method, H) and aggregated per (method, H): applied cost, normalised cost
increment vs the open-loop REL lower bound, feasibility, mean and max MPC step time (warm start + solve).

Problems run in parallel in a spawn pool; each worker loads the model(s) once. Unlike the reference's analysis,
timings of every method are reported from the same runs (no copy-paste of REL-MPC times for DIST-MPC).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ttompc.evaluation.common import EvalProblem, eval_problem, pool_map, scenario_module, worker_setup
from ttompc.evaluation.metrics import aggregate, normalized_cost_increment, write_csv, write_json
from ttompc.mpc.loop import Episode, Mode, run_mpc
from ttompc.mpc.providers import DISTProvider, Provider, RELProvider, TTOProvider
from ttompc.scenarios import get_scenario

FIELDS = (
    "cost",
    "norm_cost_increment",
    "mean_step_time",
    "max_step_time",
    "mean_iterations",
    "terminal_error",
    "keepout_violations",
    "fallbacks",
)


@dataclass
class HorizonStudyConfig:
    scenario: str
    out: str
    checkpoint: str | None = None  # TTO-MPC model (checkpoint, bundle or zoo name); None: baselines only
    ft_checkpoint: str | None = None  # FT-TTO-MPC model
    horizons: list[int] = field(default_factory=lambda: list(range(10, 101, 10)))
    problems: int = 10
    seed: int = 0
    workers: int = 1
    mode: Mode = "soft"
    max_steps: int | None = None  # truncated episodes (smoke tests)
    backend: str = "auto"
    device: str = "cpu"


_W: dict[str, Any] = {}


def _init(module: str, cfg: dict[str, Any]) -> None:
    from ttompc.policy import Planner

    worker_setup(module)
    _W["cfg"] = HorizonStudyConfig(**cfg)
    _W["scenario"] = scenario = get_scenario(cfg["scenario"])
    for key in ("checkpoint", "ft_checkpoint"):
        _W[key] = Planner.from_pretrained(cfg[key], scenario, device=cfg["device"]) if cfg[key] else None


def _providers() -> list[Provider]:
    cfg: HorizonStudyConfig = _W["cfg"]
    out: list[Provider] = [RELProvider(cfg.backend), DISTProvider(cfg.backend)]
    if _W["checkpoint"] is not None:
        out.append(TTOProvider(_W["checkpoint"], "TTO-MPC"))
    if _W["ft_checkpoint"] is not None:
        out.append(TTOProvider(_W["ft_checkpoint"], "FT-TTO-MPC"))
    return out


def _run_problem(index: int) -> list[dict[str, Any]]:
    cfg: HorizonStudyConfig = _W["cfg"]
    sc = _W["scenario"]
    ep = eval_problem(sc, cfg.seed, index, nonconvex_only=True, backend=cfg.backend)
    records = []
    for H in cfg.horizons:
        for provider in _providers():
            e = run_mpc(
                sc,
                ep.problem,
                provider,
                H,
                rel_cost=ep.rel.cost,
                mode=cfg.mode,
                max_steps=cfg.max_steps,
                backend=cfg.backend,
            )
            records.append({"problem": index, "seed": ep.seed, "ctg0": ep.ctg0, **e.summary()})
    return records


def run_horizon_study(cfg: HorizonStudyConfig) -> dict[str, Any]:
    """Run the study and write ``horizon.json``, ``horizon_runs.csv``, ``horizon_summary.csv`` and the plots into
    ``cfg.out``; returns the report."""
    from ttompc.evaluation.plots import plot_horizon

    if not cfg.horizons or min(cfg.horizons) < 1:
        raise ValueError(f"horizons must be positive integers, got {cfg.horizons}")
    sc = get_scenario(cfg.scenario)
    cfg.horizons = sorted({min(h, sc.n_steps) for h in cfg.horizons})
    t0 = time.perf_counter()
    records: list[dict[str, Any]] = []
    for rs in pool_map(_run_problem, range(cfg.problems), cfg.workers, _init, (scenario_module(sc.name), asdict(cfg))):
        records.extend(rs)
    normalized_cost_increment(records)
    summary = aggregate(records, ("method", "horizon"), FIELDS)
    out = Path(cfg.out)
    report = {
        "config": asdict(cfg),
        "scenario": {"name": sc.name, "version": sc.version, "n_steps": sc.n_steps},
        "wall_time_s": time.perf_counter() - t0,
        "summary": summary,
        "runs": records,
    }
    write_json(out / "horizon.json", report)
    write_csv(out / "horizon_runs.csv", records)
    write_csv(out / "horizon_summary.csv", summary)
    report["plots"] = [str(p) for p in plot_horizon(summary, out)]
    return report


def closed_loop_metrics(
    planner: Any,
    problems: list[EvalProblem],
    horizon: int,
    *,
    name: str = "TTO-MPC",
    mode: Mode = "soft",
    max_steps: int | None = None,
    backend: str = "auto",
) -> tuple[dict[str, float], list[Episode]]:
    """TTO-MPC with ``planner`` on fixed problems: mean cost, mean relative cost increment over the REL lower bound
    (J − J_REL)/J_REL, feasibility rate, mean/max step time and fallback count (training callback, DAgger)."""
    sc = planner.scenario
    episodes = [
        run_mpc(sc, ep.problem, TTOProvider(planner, name), horizon, rel_cost=ep.rel.cost, mode=mode,
                max_steps=max_steps, backend=backend)
        for ep in problems
    ]  # fmt: skip
    times = np.concatenate([e.step_times for e in episodes])
    metrics = {
        "cost": float(np.mean([e.cost for e in episodes])),
        "cost_increment": float(np.mean([(e.cost - e.rel_cost) / abs(e.rel_cost) for e in episodes])),
        "feasible_rate": float(np.mean([e.feasible for e in episodes])),
        "step_time_mean": float(np.mean(times)),
        "step_time_max": float(np.max(times)),
        "fallbacks": float(sum(e.fallbacks for e in episodes)),
    }
    return metrics, episodes
