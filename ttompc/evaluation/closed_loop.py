"""Closed-loop evaluation (paper §V-C, Fig. 5–6; ``docs/evaluation.md``), the protocol of ``ttompc evaluate mpc``.

For seeded held-out problems whose REL solution violates a keep-out zone, every planning horizon H and every plant
(``nominal``: the exact dynamics; ``perturbed``: seeded actuation error and process noise, ``PlantNoise``, the same
disturbances for every method of a problem), run under the settings of a protocol (``protocol``: a preset of
``ttompc.mpc.settings``, ``paper`` or ``zoo``, with single-key overrides in ``mpc``) — a ``Measurement``
(``ttompc.evaluation.measurement``) with the methods and workers that measure it (``ClosedLoopConfig``):

* REL-MPC and DIST-MPC (the paper's baselines),
* PLAN-ONCE: the open-loop SCP optimum solved at t = 0, then MPC tracking it (no model, no re-planning),
* ORACLE-MPC, the ceiling: the full remaining-horizon SCP optimum from the measured state as warm start and target,
* TTO-MPC (the paper's terminal target) and R-TTO-MPC (the robust target, ``TerminalDesign(blend)``), and the same
  for a fine-tuned model (FT-TTO-MPC, R-FT-TTO-MPC) when given.

Reported per (plant, method, H): runs, feasible and infeasible counts (infeasible or goal-missing runs are never
averaged into a cost), (J − J_REL)/J_REL over feasible runs with standard error and bootstrap interval, the paper's
normalisation (problems feasible for every method, DIST-MPC's worst horizon = 1), the paired difference to
REL-MPC on the problems both ran feasibly (fair where the feasible sets differ), the share of the reachable gain
REL-MPC → ORACLE-MPC, plan consistency (mean change of the terminal target between steps) and step times. The
report names its protocol and records the resolved settings; the settings that depart from the paper preset
(``departures``) are listed under the table.

Problems run in parallel in the spawn pool in tasks of ``batch`` problems; each worker loads the model(s) once.
Within a task the episodes of one method run in lockstep (``run_mpc_batch``): a TTO method plans the windows of all
its problems with one batched rollout per step, and the solver structures built for the first problem serve the
others (one per window shape, cached per process). Step times are then each episode's share of the batched rollout
plus its own solves (CPU cost per episode, not one robot's latency: ``bench/mpc_speed.py`` measures that at B = 1).
Tasks are fixed by ``batch``, not by ``workers``, so the report does not depend on the number of workers.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ttompc.errors import UserError
from ttompc.evaluation.episodes import episode_record, summarize_episodes
from ttompc.evaluation.measurement import PLANTS, Measurement
from ttompc.evaluation.metrics import format_gain_share, gain_share, paper_normalized, write_csv, write_json
from ttompc.evaluation.problems import EvalProblem
from ttompc.evaluation.stats import format_interval, interval
from ttompc.evaluation.warmstart import default_workers
from ttompc.mpc.loop import run_mpc_batch
from ttompc.mpc.providers import (
    DISTProvider,
    OracleProvider,
    PlanProvider,
    Provider,
    RELProvider,
    TerminalDesign,
    full_horizon_plan,
)
from ttompc.mpc.settings import MPCSettings
from ttompc.mpc.tto import check_rtg_scale, effective_rtg_mode, tracking_design, tto_providers
from ttompc.parallel import WorkerState, pool_map
from ttompc.progress import Bar
from ttompc.scenarios import get_scenario, scenario_spec
from ttompc.scenarios.base import Scenario
from ttompc.solvers.backends import solver_path

if TYPE_CHECKING:
    from ttompc.policy import Planner

BASELINE, CEILING, REFERENCE = "REL-MPC", "ORACLE-MPC", "DIST-MPC"
BASELINE_METHODS = 4  # REL-MPC, DIST-MPC, PLAN-ONCE and ORACLE-MPC: the providers() of every problem, model or not


@dataclass
class ClosedLoopConfig(Measurement):
    """``ttompc evaluate mpc`` settings (``key=value`` on the command line): a ``Measurement`` (protocol, overrides,
    problems, seed, horizons, plants, the perturbed plant, max_steps), by default on both plants, and the methods
    and workers that measure it."""

    plants: list[str] = field(default_factory=lambda: list(PLANTS))
    model: str | None = None  # TTO model: zoo name, hf://ORG/NAME[@REV], bundle folder or .ckpt; None: baselines only
    ft_model: str | None = None  # FT-TTO model, same forms
    scenario: str | None = None  # default: the model's scenario
    robust_blend: float = 0.95  # target blend of the R-TTO-MPC variants (docs/evaluation.md); 0 leaves them out
    rtg_scale: float | None = None  # rtg_0 = −rtg_scale·J_REL; None: the model's own (Planner.rtg_scale)
    batch: int = 10  # problems per pool task, their episodes in lockstep (one batched rollout per step)
    workers: int = 0  # processes; 0 = one per CPU core
    device: str = "cpu"
    out: str = ""  # default: outputs/evaluate/mpc-<scenario>

    def __post_init__(self) -> None:
        super().__post_init__()
        TerminalDesign(self.robust_blend)  # validates the blend
        if self.rtg_scale is not None:
            check_rtg_scale(self.rtg_scale)
        if self.batch < 1:
            raise ValueError(f"batch must be >= 1, got {self.batch}")


def providers(
    plans: Sequence[tuple[np.ndarray, np.ndarray]],
    models: dict[str, Planner],
    settings: MPCSettings,
    *,
    robust_blend: float = 0.95,
    rtg_scale: float | None = None,
) -> list[list[Provider]]:
    """Fresh providers of every method, one per problem: ``plans`` are the problems' open-loop SCP optima
    (``full_horizon_plan``), shared by PLAN-ONCE and ORACLE-MPC. The TTO providers of one method share a
    ``RolloutGroup`` (one batched rollout per lockstep step; ``tto_providers``). ``settings`` give the plan-tracking
    weight, the rtg mode and the backend."""
    backend = settings.backend
    plain = tracking_design(settings)
    out: list[list[Provider]] = [
        [RELProvider(backend) for _ in plans],
        [DISTProvider(backend) for _ in plans],
        [PlanProvider(plan, backend=backend, design=plain) for plan in plans],
        [OracleProvider(plan, backend=backend, design=plain) for plan in plans],
    ]
    blends = {"": 0.0} | ({"R-": robust_blend} if robust_blend > 0 else {})
    for name, planner in models.items():
        mode = effective_rtg_mode(settings.rtg_mode, planner)
        # a method fed another rtg than the paper's ledger says so in its name (the oracle's is a ceiling, not a method)
        suffix = "" if mode == "running" else f"[rtg={mode}]"
        for prefix, blend in blends.items():
            out.append([*tto_providers(planner, settings, plans, f"{prefix}{name}-MPC{suffix}", blend=blend,
                                       rtg_scale=rtg_scale)])  # fmt: skip
    return out


def run_problems(
    scenario: Scenario,
    eps: Sequence[EvalProblem],
    models: dict[str, Planner],
    cfg: ClosedLoopConfig,
    on_episode: Callable[[], None] | None = None,
) -> tuple[list[dict[str, Any]], dict[tuple[str, str, int, int], np.ndarray]]:
    """Every (plant, H, method) episode of the problems ``eps`` under the measurement ``cfg``, the episodes of one
    method in lockstep: records (per problem, then plant, H and method) and executed trajectories by (plant, method,
    H, problem index). ``on_episode`` is called after each episode (a progress bar's ticker)."""
    records: list[dict[str, Any]] = []
    trajectories = {}
    s = cfg.settings
    plans = [full_horizon_plan(scenario, ep.problem, s.backend) for ep in eps]
    starts = [ep.start for ep in eps]
    for plant, run in cfg.runs(scenario):
        for method in providers(plans, models, s, robust_blend=cfg.robust_blend, rtg_scale=cfg.rtg_scale):
            episodes = run_mpc_batch(scenario, starts, method, run)
            for ep, e in zip(eps, episodes, strict=True):
                records.append({"problem": ep.index, "seed": ep.seed, "ctg0": ep.ctg0, **episode_record(e)})
                trajectories[(plant, e.method, run.horizon, ep.index)] = e.X
                if on_episode is not None:
                    on_episode()
    records.sort(key=lambda r: r["problem"])  # stable: plant, H and method order within a problem
    return records, trajectories


def run_problem(
    scenario: Scenario,
    ep: EvalProblem,
    models: dict[str, Planner],
    cfg: ClosedLoopConfig,
    on_episode: Callable[[], None] | None = None,
) -> tuple[list[dict[str, Any]], dict[tuple[str, str, int], np.ndarray]]:
    """``run_problems`` for one problem: records and executed trajectories by (plant, method, H)."""
    records, trajectories = run_problems(scenario, [ep], models, cfg, on_episode)
    return records, {key[:3]: X for key, X in trajectories.items()}


def episodes_per_problem(cfg: ClosedLoopConfig, models: int) -> int:
    """How many episodes ``run_problem`` runs with ``models`` models: every plant, horizon and method of
    ``providers`` (the robust variant of each model unless ``robust_blend`` is 0)."""
    methods = BASELINE_METHODS + models * (2 if cfg.robust_blend > 0 else 1)
    return len(cfg.plants) * len(cfg.horizons) * methods


@dataclass
class _Worker:
    """What ``_init`` loads once per pool worker for ``_run``."""

    cfg: ClosedLoopConfig
    scenario: Scenario
    models: dict[str, Planner]
    tick: Callable[[], None]


_WORKER: WorkerState[_Worker] = WorkerState()


def _init(cfg: dict[str, Any], tick: Callable[[], None]) -> None:
    from ttompc.config import from_container
    from ttompc.policy import Planner

    c = from_container(ClosedLoopConfig, cfg)
    assert c.scenario is not None  # the caller resolved it before starting the workers
    scenario = get_scenario(c.scenario)
    models = {
        name: Planner.from_pretrained(src, scenario, device=c.device)
        for name, src in (("TTO", c.model), ("FT-TTO", c.ft_model))
        if src
    }
    _WORKER.set(_Worker(c, scenario, models, tick))


def _run(indices: tuple[int, ...]) -> list[dict[str, Any]]:
    w = _WORKER.get()
    cfg, sc = w.cfg, w.scenario
    return run_problems(sc, cfg.problem_set(sc, indices), w.models, cfg, w.tick)[0]


def tasks(problems: int, batch: int) -> list[tuple[int, ...]]:
    """Problem indices 0..problems-1 in pool tasks of ``batch`` (the last one shorter)."""
    return [tuple(range(i, min(i + batch, problems))) for i in range(0, problems, batch)]


def departures(settings: MPCSettings, scenario: Scenario) -> list[str]:
    """The settings of a run that depart from the paper (and from the authors' code), one sentence each."""
    out = []
    track = scenario.mpc.tracking if settings.track is None else settings.track
    if track != scenario.mpc.terminal:
        out.append(
            f"plan-tracking terminal weight {track:g} for TTO-MPC, PLAN-ONCE and ORACLE-MPC (the paper: "
            f"{scenario.mpc.terminal:g}, below the terminal multipliers of optimal plans; docs/evaluation.md)"
        )
    if settings.end_horizon > 0:
        out.append(
            f"shrinking end horizon: windows run to N once N − t <= {settings.end_horizon} (the paper keeps H and "
            "truncates the windows at N)"
        )
    if settings.rtg_mode != "running":
        out.append(
            f"reward-to-go fed in closed loop: {settings.rtg_mode} (the paper: the running rtg_0 + executed cost)"
        )
    if settings.finish > 0:
        out.append(
            f"finish cost (weight {settings.finish:g}): windows that stop before N also pay the price of reaching the "
            "goal from their last state in the steps left (ttompc.mpc.finish; the paper: the terminal target alone)"
        )
    if settings.mode != "soft":
        out.append(f"{settings.mode} end condition (the paper's analyses: soft)")
    if settings.rti:
        out.append(
            "real-time iteration: one SCP subproblem per MPC step from the previous solution shifted (the paper "
            "solves every window to convergence)"
        )
    return out


def protocol_label(cfg: Measurement) -> str:
    """How a report names its protocol: the preset, and the overrides when there are any."""
    overrides = " ".join(f"mpc.{k}={v}" for k, v in cfg.mpc.items())
    return f"{cfg.protocol} {overrides}" if overrides else cfg.protocol


def summarize(records: list[dict[str, Any]], seed: int = 0) -> list[dict[str, Any]]:
    """Rows per (plant, method, horizon): ``summarize_episodes`` + paper normalisation + share of reachable gain."""
    rows = []
    for plant in sorted({r["plant"] for r in records}):
        recs = [r for r in records if r["plant"] == plant]
        methods = list(dict.fromkeys(r["method"] for r in recs))
        paper = {(p["method"], p["horizon"]): p for p in paper_normalized(recs, methods, REFERENCE, seed=seed)}
        for m in methods:
            for H in sorted({r["horizon"] for r in recs}):
                group = [r for r in recs if r["method"] == m and r["horizon"] == H]
                row: dict[str, Any] = {
                    "plant": plant,
                    "method": m,
                    "horizon": H,
                    **summarize_episodes(group, seed=seed),
                }
                if (m, H) in paper:
                    row["paper_norm"] = paper[(m, H)]["paper_norm"]
                    row["paper_problems"] = paper[(m, H)]["problems"]
                if m != BASELINE:  # paired with REL-MPC on the problems both ran feasibly (nan = infeasible)
                    inc = {
                        k: {r["problem"]: r["rel_increment"] for r in recs if r["method"] == k and r["horizon"] == H}
                        for k in (BASELINE, m)
                    }
                    row["vs_rel_mpc"] = interval(
                        [v - inc[BASELINE][p] for p, v in inc[m].items() if p in inc[BASELINE]], seed=seed
                    )
                if m not in (BASELINE, CEILING):
                    cost = {
                        k: {r["problem"]: (r["cost"] if r["feasible"] else np.nan) for r in recs
                            if r["method"] == k and r["horizon"] == H}
                        for k in (BASELINE, m, CEILING)
                    }  # fmt: skip
                    probs = sorted(cost[m])
                    row["gain_share"] = gain_share(
                        *(np.array([cost[k].get(p, np.nan) for p in probs]) for k in (BASELINE, m, CEILING)), seed=seed
                    )
                rows.append(row)
    return rows


def headline(records: list[dict[str, Any]], seed: int = 0) -> list[dict[str, Any]]:
    """The paper's headline comparison, when more than one horizon ran: every method at the shortest horizon against
    REL-MPC at the longest, per plant: goals reached, the paired difference in (J − J_REL)/J_REL over the problems
    both reach feasibly, and how many times lower the mean step time is. Empty for a single horizon."""
    horizons = sorted({r["horizon"] for r in records})
    if len(horizons) < 2:
        return []
    short, long = horizons[0], horizons[-1]
    rows = []
    for plant in sorted({r["plant"] for r in records}):
        base = [r for r in records if r["plant"] == plant and r["method"] == BASELINE and r["horizon"] == long]
        ref = {r["problem"]: r for r in base}
        for m in dict.fromkeys(r["method"] for r in records if r["plant"] == plant):
            group = [r for r in records if r["plant"] == plant and r["method"] == m and r["horizon"] == short]
            both = [(r, ref[r["problem"]]) for r in group
                    if r["feasible"] and r["problem"] in ref and ref[r["problem"]]["feasible"]]  # fmt: skip
            rows.append({
                "plant": plant, "method": m, "horizon": short, "baseline_horizon": long, "runs": len(group),
                "feasible": sum(r["feasible"] for r in group), "baseline_feasible": sum(r["feasible"] for r in base),
                "vs_baseline": interval([a["rel_increment"] - b["rel_increment"] for a, b in both], seed=seed),
                "step_ratio": float(np.mean([r["mean_step_time"] for r in base])
                                    / np.mean([r["mean_step_time"] for r in group])),
            })  # fmt: skip
    return rows


def format_headline(rows: list[dict[str, Any]]) -> str:
    """A markdown table of ``headline`` (empty string when there is none)."""
    if not rows:
        return ""
    H, long = rows[0]["horizon"], rows[0]["baseline_horizon"]
    lines = [
        f"\n### Against {BASELINE}@{long}: every method at H = {H}\n",
        f"| plant | method | goals | {BASELINE}@{long} goals | paired vs {BASELINE}@{long}, points (n) "
        f"| step time vs {BASELINE}@{long} |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        vs = r["vs_baseline"]
        paired = f"{format_interval(vs, 100)} ({vs['n']})" if vs["n"] else "–"
        lines.append(
            f"| {r['plant']} | {r['method']} | {r['feasible']}/{r['runs']} | {r['baseline_feasible']}/{r['runs']} "
            f"| {paired} | {r['step_ratio']:.1f}× lower |"
        )
    return "\n".join(lines)


def format_table(summary: list[dict[str, Any]]) -> str:
    """A readable markdown table of ``summarize``."""
    lines = [
        "| plant | method | H | feasible | (J − J_REL)/J_REL, % (mean ± s.e. [95% CI]) | paired vs REL-MPC, points "
        "(n) | paper norm. | share of reachable gain, % | goal miss of infeasible runs [m] | target change "
        "| mean / max step [ms] |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in summary:
        paper = format_interval(r["paper_norm"], 1, 2) if "paper_norm" in r else "–"
        share = format_gain_share(r["gain_share"]) if "gain_share" in r else "–"
        vs = r.get("vs_rel_mpc")
        paired = f"{format_interval(vs, 100)} ({vs['n']})" if vs and vs["n"] else "–"
        lines.append(
            f"| {r['plant']} | {r['method']} | {r['horizon']} | {r['feasible']}/{r['runs']} "
            f"| {format_interval(r['rel_increment'], 100)} | {paired} | {paper} | {share} "
            f"| {format_interval(r['infeasible_terminal_error'], 1, 2)} | {r['target_change']['mean']:.3g} "
            f"| {r['mean_step_time'] * 1e3:.0f} / {r['max_step_time'] * 1e3:.0f} |"
        )
    for plant in dict.fromkeys(r["plant"] for r in summary):
        n = max((r.get("paper_problems", 0) for r in summary if r["plant"] == plant), default=0)
        lines.append(
            f"\n{plant} plant: paper normalisation over {n} problems feasible for every method."
            if n
            else f"\n{plant} plant: paper normalisation undefined (no problem on which every method is feasible, or "
            "DIST-MPC never costs more than J_REL)."
        )
    lines.append(
        "Costs average feasible runs only; infeasible runs (keep-out, path or goal tolerance violated) are counted "
        "in 'feasible' and described by their goal miss. Paired vs REL-MPC: the mean per-problem difference in "
        "(J − J_REL)/J_REL over the n problems both ran feasibly (negative: cheaper). Share of reachable gain: "
        "REL-MPC = 0, ORACLE-MPC = 100; "
        "undefined when the reachable gain (REL-MPC − ORACLE-MPC cost) is within noise."
    )
    return "\n".join(lines)


def run_closed_loop(cfg: ClosedLoopConfig) -> dict[str, Any]:
    """Run the study; writes ``mpc.json``, ``mpc.md`` (the table), ``mpc_runs.csv`` and plots into ``cfg.out``."""
    from ttompc.config import to_container
    from ttompc.evaluation.plots import plot_horizon

    if cfg.scenario is None:
        raise ValueError("ClosedLoopConfig.scenario is not set (the command takes it from the model)")
    sc = get_scenario(cfg.scenario)
    too_long = sorted({h for h in cfg.horizons if h > sc.n_steps})
    if too_long:  # refused, not clipped: a clipped horizon would report under a number that was never run
        raise UserError(
            f"horizons {too_long} exceed the horizon of {sc.name}, N = {sc.n_steps} steps",
            f"pass horizons of at most {sc.n_steps} (horizons=[{sc.n_steps}] plans the whole remaining episode)",
        )
    cfg.horizons = sorted(set(cfg.horizons))
    out = Path(cfg.out or f"outputs/evaluate/mpc-{sc.name}")
    workers = default_workers(cfg.workers)
    t0 = time.perf_counter()
    records: list[dict[str, Any]] = []
    models = sum(1 for source in (cfg.model, cfg.ft_model) if source)
    with Bar(cfg.problems * episodes_per_problem(cfg, models), f"mpc {sc.name}", "episode") as bar:
        init = (to_container(cfg), bar.ticker())
        chunks = tasks(cfg.problems, cfg.batch)
        for rs in pool_map(_run, chunks, workers, _init, init, scenarios=[scenario_spec(sc)]):
            records.extend(rs)
    summary = summarize(records, cfg.seed)
    settings = cfg.settings
    notes = departures(settings, sc)
    head = headline(records, cfg.seed)
    table = format_table(summary) + f"\nProtocol: {protocol_label(cfg)}."
    if notes:
        table += "\nDepartures from the paper: " + "; ".join(notes) + "."
    table += format_headline(head)
    report = {
        "config": {**asdict(cfg), "out": str(out), "workers": workers},
        "protocol": {"name": protocol_label(cfg), "settings": asdict(settings)},
        "solver": solver_path(settings.backend, sc),
        "scenario": {"name": sc.name, "version": sc.version, "n_steps": sc.n_steps},
        "perturbed_plant": asdict(cfg.plant.resolve(sc)),  # the disturbance the perturbed episodes met
        "wall_time_s": time.perf_counter() - t0,
        "departures": notes,
        "summary": summary,
        "headline": head,
        "table": table,
        "runs": records,
    }
    write_json(out / "mpc.json", report)
    (out / "mpc.md").write_text(f"# Closed loop: {sc.name}, {cfg.problems} problems\n\n{table}\n")
    write_csv(out / "mpc_runs.csv", records)
    report["plots"] = [str(p) for p in plot_horizon(summary, out)]
    report["out"] = str(out)
    return report
