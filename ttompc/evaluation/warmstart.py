"""Open-loop warm-start evaluation (paper §V-B, Fig. 4; ``docs/evaluation.md``), the protocol of ``ttompc evaluate
warmstart`` and the demo.

For seeded held-out problems (non-convex by default: the REL solution violates a keep-out zone): REL (timed) → SCP
from the REL warm start, versus a transformer rollout conditioned on rtg_0 = −κ·J_REL (κ = ``rtg_scale``, the
paper: 1), ctg_0 = 0 → SCP from that warm start (TTO, and FT-TTO when a second model is given). The ceiling,
ORACLE, is the best optimum the SCP reaches from several warm starts: REL, every model, the straight line and
``oracle_detours`` seeded random detours around REL. Per problem: cost, suboptimality (J − J_REL)/J_REL, SCP
iterations, runtime (warm start + SCP), success. Reported per method: failures counted apart, means with standard
error and bootstrap interval over the solved problems, the share of the reachable gain (SCP(REL) → ORACLE) a model
captures; per non-convexity bin, and Fig. 4's % improvement over the REL warm start.

Our SCP returns its best feasible iterate, so "cost" is the reference's min(J_vect) and the returned trajectory at
once; iteration counts are the number of convex subproblems solved.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ttompc.evaluation.metrics import (
    aggregate,
    format_gain_share,
    gain_share,
    improvement_by_threshold,
    write_csv,
)
from ttompc.evaluation.problems import EvalProblem, eval_problem
from ttompc.evaluation.report_files import check_replaceable, claim_report, finish, retract
from ttompc.evaluation.reproduce import report_command
from ttompc.evaluation.stats import format_interval, interval
from ttompc.model_slots import MODEL_SLOTS
from ttompc.mpc.tto import check_rtg_scale
from ttompc.parallel import WorkerState, pool_map
from ttompc.progress import Bar
from ttompc.ranges import Checked, check_devices, setting
from ttompc.scenarios import get_scenario, scenario_spec
from ttompc.scenarios.base import Scenario, Window
from ttompc.seeding import rng
from ttompc.solvers.backends import solver_path
from ttompc.solvers.scp import SCPOptions, SCPProblem, SCPResult, solve_scp

if TYPE_CHECKING:
    from ttompc.policy import Planner

BASELINE = "REL"
ORACLE = "ORACLE"
ORACLE_STREAM = 0x6F72636C  # "orcl": seeds of the oracle's random detours
DETOUR_SIZE = 0.3  # detour amplitude in units of the scenario's state_scale


@dataclass
class WarmStartConfig(Checked):
    """``ttompc evaluate warmstart`` settings (``key=value`` on the command line)."""

    model: str | None = None  # TTO model: zoo name, hf://ORG/NAME[@REV], bundle folder or .ckpt
    ft_model: str | None = None  # FT-TTO model, same forms
    scenario: str | None = None  # default: the model's scenario
    problems: int = setting(100, ge=1)
    seed: int = setting(0, ge=0)  # root seed of the held-out evaluation stream
    nonconvex_only: bool = True  # keep problems whose REL solution violates a keep-out zone
    # rtg_0 = −rtg_scale·J_REL; None: the model's own (Planner.rtg_scale); its range: check_rtg_scale
    rtg_scale: float | None = setting(None)
    # random detours tried by the oracle (besides REL, models and the straight line)
    oracle_detours: int = setting(4, ge=0)
    workers: int = setting(0, ge=0, per_core=4, meaning="0: one per CPU core")  # processes
    # suboptimality thresholds of the improvement curve
    thresholds: list[float] = setting(
        factory=lambda: [round(0.1 * i, 1) for i in range(10)], ge=0, nonempty=True, unique=True
    )
    backend: str = "auto"
    device: str = setting("cpu", device="torch")
    out: str = ""  # default: outputs/evaluate/warmstart-<scenario>

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.rtg_scale is not None:
            check_rtg_scale(self.rtg_scale)


def default_workers(workers: int) -> int:
    return workers if workers > 0 else os.cpu_count() or 1


def _record(row: dict[str, Any], name: str, res: SCPResult, ws_time: float, rel_cost: float) -> None:
    row[f"{name}_success"] = bool(res.success)
    row[f"{name}_cost"] = float(res.cost) if res.success else float("nan")
    row[f"{name}_suboptimality"] = float((res.cost - rel_cost) / rel_cost) if res.success else float("nan")
    row[f"{name}_iterations"] = int(res.iterations)
    row[f"{name}_warmstart_time"] = ws_time
    row[f"{name}_scp_time"] = float(res.solve_time)
    row[f"{name}_time"] = ws_time + float(res.solve_time)


def detours(scenario: Scenario, ep: EvalProblem, count: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``count`` seeded warm starts: REL's states plus a smooth bump sin(πk/N)·DETOUR_SIZE·state_scale·z (one
    random direction z per detour), REL's controls; drawn from the problem's seed, so they are reproducible."""
    X, U = ep.rel.X, ep.rel.U
    n = X.shape[1]
    scale = scenario.state_units()
    bump = np.sin(np.pi * np.arange(len(X)) / (len(X) - 1))[:, None]
    g = rng(ep.seed, ORACLE_STREAM)
    out = []
    for _ in range(count):
        Xd = X + bump * DETOUR_SIZE * scale * g.standard_normal(n)
        Xd[0] = X[0]
        out.append((Xd, U.copy()))
    return out


def evaluate_problem(
    scenario: Scenario,
    ep: EvalProblem,
    models: dict[str, Planner],
    *,
    rtg_scale: float | None = None,
    oracle_detours: int = 4,
    backend: str = "auto",
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """One problem of the protocol: SCP from REL, from every model's rollout and the oracle's best optimum.
    Returns the report row and the trajectories (label -> states) for plots."""
    p, rel = ep.problem, ep.rel
    row: dict[str, Any] = {"problem": ep.index, "seed": ep.seed, "ctg0": ep.ctg0, "rel_cost": rel.cost}
    scp, options = SCPProblem(scenario, p), SCPOptions(backend=backend)
    scp_rel = solve_scp(scp, rel.X, rel.U, options)
    _record(row, BASELINE, scp_rel, ep.rel_time, rel.cost)
    trajectories = {"REL (lower bound)": rel.X, "SCP from REL": scp_rel.X}
    optima = [scp_rel]
    for name, planner in models.items():
        t0 = time.perf_counter()
        kappa = planner.rtg_scale if rtg_scale is None else rtg_scale
        X, U = planner.warm_start([p], rtg0=-kappa * rel.cost, ctg0=0.0)
        ws_time = time.perf_counter() - t0
        res = solve_scp(scp, X[0], U[0], options)
        _record(row, name, res, ws_time, rel.cost)
        trajectories[f"{name} rollout"] = X[0]
        trajectories[f"SCP from {name}"] = res.X
        optima.append(res)
    starts = [scenario.initial_guess(p, Window.full(p)), *detours(scenario, ep, oracle_detours)]
    optima += [solve_scp(scp, X, U, options) for X, U in starts]
    solved = [r for r in optima if r.success]
    best = min(solved, key=lambda r: r.cost) if solved else scp_rel
    _record(row, ORACLE, best, 0.0, rel.cost)
    row[f"{ORACLE}_starts"] = len(optima)
    trajectories["ORACLE (best optimum)"] = best.X
    return row, trajectories


@dataclass
class _Worker:
    """What ``_init`` loads once per pool worker for ``_run_problem``."""

    cfg: WarmStartConfig
    scenario: Scenario
    models: dict[str, Planner]


_WORKER: WorkerState[_Worker] = WorkerState()


def _init(cfg: dict[str, Any]) -> None:
    from ttompc.policy import Planner

    scenario = get_scenario(cfg["scenario"])
    models = {
        name: Planner.from_pretrained(cfg[key], scenario, device=cfg["device"])
        for name, key in MODEL_SLOTS.items()
        if cfg[key]
    }
    _WORKER.set(_Worker(WarmStartConfig(**cfg), scenario, models))


def _run_problem(index: int) -> dict[str, Any]:
    w = _WORKER.get()
    cfg, sc = w.cfg, w.scenario
    ep = eval_problem(sc, cfg.seed, index, nonconvex_only=cfg.nonconvex_only, backend=cfg.backend)
    row, _ = evaluate_problem(
        sc, ep, w.models, rtg_scale=cfg.rtg_scale, oracle_detours=cfg.oracle_detours, backend=cfg.backend
    )
    return row


def method_summary(rows: list[dict[str, Any]], methods: list[str], seed: int = 0) -> list[dict[str, Any]]:
    """Per method: runs, failures (counted apart), suboptimality/iterations intervals over solved problems, mean
    times, and (models) the paired differences to REL on the problems both solved (``vs_rel``: suboptimality and
    iterations, negative = better than REL) and the share of the reachable gain between SCP(REL) and the oracle."""
    out = []
    for m in methods:
        ok = [r for r in rows if r[f"{m}_success"]]
        entry: dict[str, Any] = {
            "method": m,
            "runs": len(rows),
            "failures": len(rows) - len(ok),
            "suboptimality": interval([r[f"{m}_suboptimality"] for r in ok], seed=seed),
            "iterations": interval([r[f"{m}_iterations"] for r in ok], seed=seed),
            "time": float(np.mean([r[f"{m}_time"] for r in ok])) if ok else float("nan"),
        }
        if m not in (BASELINE, ORACLE):
            both = [r for r in ok if r[f"{BASELINE}_success"]]
            entry["vs_rel"] = {
                k: interval([r[f"{m}_{k}"] - r[f"{BASELINE}_{k}"] for r in both], seed=seed)
                for k in ("suboptimality", "iterations")
            }
            entry["gain_share"] = gain_share(
                *(np.array([r[f"{k}_cost"] for r in rows]) for k in (BASELINE, m, ORACLE)), seed=seed
            )
        out.append(entry)
    return out


def format_table(summary: list[dict[str, Any]]) -> str:
    """A readable table of ``method_summary``."""
    lines = [
        "| method | solved | suboptimality vs J_REL, % (mean ± s.e. [95% CI]) | SCP iterations | time [s] "
        "| paired vs REL: suboptimality, points; iterations | share of reachable gain, % |",
        "|---|---|---|---|---|---|---|",
    ]
    for e in summary:
        share = format_gain_share(e["gain_share"]) if "gain_share" in e else "–"
        paired = "–"
        if "vs_rel" in e:
            d = e["vs_rel"]
            paired = f"{format_interval(d['suboptimality'], 100)}; {format_interval(d['iterations'])}"
        lines.append(
            f"| {e['method']} | {e['runs'] - e['failures']}/{e['runs']} | {format_interval(e['suboptimality'], 100)} "
            f"| {format_interval(e['iterations'])} | {e['time']:.3f} | {paired} | {share} |"
        )
    return "\n".join(lines)


def run_warmstart(cfg: WarmStartConfig) -> dict[str, Any]:
    """Run the evaluation; writes ``warmstart.md`` (the table), ``warmstart_problems.csv``,
    ``warmstart_thresholds.csv``, ``warmstart_bins.csv``, ``warmstart_improvement.png`` and last ``warmstart.json``
    (marked complete: ``report_files.finish``) into ``cfg.out`` (default ``outputs/evaluate/warmstart-<scenario>``),
    a folder claimed before any work (``report_files.claim_report``: new, empty or a warm-start report's), replacing
    an earlier report of the same configuration and refusing one of another (``report_files.check_replaceable``); the
    report records its config and the command line that reproduces it (``command``, ``reproduce.report_command``)."""
    from ttompc.evaluation.plots import plot_warmstart

    if cfg.scenario is None:
        raise ValueError("WarmStartConfig.scenario is not set (the command takes it from the model)")
    check_devices(cfg)  # its device and workers exist here, as ``ttompc evaluate warmstart`` checks them
    sc = get_scenario(cfg.scenario)
    out = claim_report(cfg.out or f"outputs/evaluate/warmstart-{sc.name}", "warmstart")
    t0 = time.perf_counter()
    workers = default_workers(cfg.workers)
    config = {**asdict(cfg), "out": str(out), "workers": workers}
    check_replaceable(out / "warmstart.json", "warmstart", config)  # before any problem is solved
    with Bar(cfg.problems, f"warmstart {sc.name}", "problem") as bar:
        tasks = range(cfg.problems)
        done = pool_map(_run_problem, tasks, workers, _init, (asdict(cfg),), scenarios=[scenario_spec(sc)])
        rows = list(bar.each(done))
    models = [slot for slot, key in MODEL_SLOTS.items() if getattr(cfg, key)]
    cmax = max((r["ctg0"] for r in rows), default=0)
    for r in rows:
        r["nonconvexity"] = r["ctg0"] / cmax if cmax > 0 else 0.0
        r["bin"] = min(float(np.floor(r["nonconvexity"] * 10) / 10), 0.9)
    names = [BASELINE, *models, ORACLE]
    summary = method_summary(rows, names, cfg.seed)
    fields = [f"{m}_{f}" for m in names for f in ("suboptimality", "iterations", "time")]
    bins = aggregate(rows, ("bin",), fields)
    thresholds = improvement_by_threshold(rows, [*models, ORACLE], BASELINE, cfg.thresholds)
    table = format_table(summary)
    report = {
        "config": config,
        # the line that reproduces the report (``reproduce``)
        "command": report_command("warmstart", config, WarmStartConfig()),
        "scenario": {"name": sc.name, "version": sc.version, "n_steps": sc.n_steps},
        "solver": solver_path(cfg.backend, sc),
        "wall_time_s": time.perf_counter() - t0,
        "max_ctg0": cmax,
        "methods": summary,
        "table": table,
        "bins": bins,
        "thresholds": thresholds,
        "problems": rows,
    }
    out.mkdir(parents=True, exist_ok=True)
    retract(out / "warmstart.json")
    (out / "warmstart.md").write_text(f"# Open-loop warm starts: {sc.name}, {len(rows)} problems\n\n{table}\n")
    write_csv(out / "warmstart_problems.csv", rows)
    write_csv(out / "warmstart_thresholds.csv", thresholds)
    write_csv(out / "warmstart_bins.csv", bins)
    report["plots"] = [str(plot_warmstart(thresholds, [*models, ORACLE], out))]
    finish(out / "warmstart.json", report)  # last, marked complete
    report["out"] = str(out)
    return report
