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

The report (``ttompc.evaluation.closed_loop_report``): per (plant, method, H) counts, relative cost increments with
intervals, the paper's normalisation, the paired difference to REL-MPC, the share of the reachable gain, plan
consistency and step times, under the protocol's name and resolved settings and the departures from the paper.

Problems run in parallel in the spawn pool in tasks of ``batch`` problems; each worker loads the model(s) once.
Within a task the episodes of one method run in lockstep (``run_mpc_batch``): a TTO method plans the windows of all
its problems with one batched rollout per step, and the solver structures built for the first problem serve the
others (one per window shape, cached per process). Step times (``Episode.step_times``: observe of the previous
outcome + warm start + solve) are then each episode's share of the batched rollout and context advance plus its own
solves (CPU cost per episode, not one robot's latency: ``bench/mpc_speed.py`` measures that at B = 1).
Tasks are fixed by ``batch``, not by ``workers``, so the report does not depend on the number of workers.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ttompc.errors import UserError
from ttompc.evaluation.closed_loop_report import write_report
from ttompc.evaluation.episodes import episode_record
from ttompc.evaluation.measurement import PLANTS, Measurement
from ttompc.evaluation.problems import EvalProblem
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

if TYPE_CHECKING:
    from ttompc.policy import Planner

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
    blends = [0.0, robust_blend] if robust_blend > 0 else [0.0]
    for name, planner in models.items():
        for blend in blends:
            method = tto_method(name, planner, settings, blend)
            out.append([*tto_providers(planner, settings, plans, method, blend=blend, rtg_scale=rtg_scale)])
    return out


def tto_method(name: str, planner: Planner, settings: MPCSettings, blend: float) -> str:
    """The method name of TTO-MPC with ``planner`` in the model slot ``name`` ("TTO", "FT-TTO") under ``settings``
    and target blend ``blend``, as the report names it: "R-" for a robust target (blend > 0), and "[rtg=MODE]" when
    the model is fed another rtg than the paper's ledger (``effective_rtg_mode``; the oracle's is a ceiling, not a
    method), e.g. R-FT-TTO-MPC[rtg=value]."""
    mode = effective_rtg_mode(settings.rtg_mode, planner)
    suffix = "" if mode == "running" else f"[rtg={mode}]"
    return f"{'R-' if blend > 0 else ''}{name}-MPC{suffix}"


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


def run_closed_loop(cfg: ClosedLoopConfig) -> dict[str, Any]:
    """Run the study; writes ``mpc.json``, ``mpc.md`` (the table), ``mpc_runs.csv`` and plots into ``cfg.out``
    (``closed_loop_report.write_report``)."""
    from ttompc.config import to_container

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
    return write_report(cfg, sc, records, out, workers, t0)
