"""Closed-loop evaluation (paper §V-C, Fig. 5–6; ``docs/evaluation.md``), the protocol of ``ttompc evaluate mpc``.

For seeded held-out problems whose REL solution violates a keep-out zone, every planning horizon H and every plant
(``nominal``: the exact dynamics; ``perturbed``: seeded actuation error and process noise, ``PlantNoise``, the same
disturbances for every method of a problem), run under the settings of a protocol (``protocol``: a preset of
``ttompc.mpc.settings``, ``paper`` or ``zoo``, with single-key overrides in ``mpc``) — a ``Measurement``
(``ttompc.evaluation.measurement``) with the models and workers that measure it (``ClosedLoopConfig``) — the
methods of ``ttompc.mpc.methods`` that the given models allow (``methods_for``): REL-MPC and DIST-MPC (the paper's
baselines), PLAN-ONCE, ORACLE-MPC (the ceiling), TTO-MPC and R-TTO-MPC (the robust target, left out when
``robust_blend`` is 0) with ``model``, and FT-TTO-MPC and R-FT-TTO-MPC with ``ft_model``.

The report (``ttompc.evaluation.closed_loop_report``): per (plant, method, H) counts, relative cost increments with
intervals, the paper's normalisation, the paired difference to REL-MPC, the share of the reachable gain, plan
consistency and step times, under the protocol's name and resolved settings and the departures from the paper.

The study is a resumable sweep (``run_closed_loop``): problems run in parallel in the spawn pool in tasks of ``batch``
problems on one plant at one horizon (``sweep_tasks``); each worker loads the model(s) once and builds each problem
once. The records of a task are stored in the report folder as it finishes (``ttompc.evaluation.episode_store``): a
run of the same configuration into the same folder runs only the tasks not yet stored. Within a task the episodes
of one method run in lockstep (``run_mpc_batch``): a TTO method plans the windows of all
its problems with one batched rollout per step, and the solver structures built for the first problem serve the
others (one per window shape, cached per process). Step times (``Episode.step_times``: observe of the previous
outcome + warm start + solve) are then each episode's share of the batched rollout and context advance plus its own
solves (CPU cost per episode, not one robot's latency: ``bench/mpc_speed.py`` measures that at B = 1).
Tasks are fixed by ``batch``, not by ``workers``, so the report does not depend on the number of workers.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Collection, Sequence
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

from ttompc.errors import UserError
from ttompc.evaluation.closed_loop_report import write_report
from ttompc.evaluation.episode_store import EpisodeStore, fingerprint
from ttompc.evaluation.episodes import episode_record
from ttompc.evaluation.machine import load_average
from ttompc.evaluation.measurement import PLANTS, Measurement
from ttompc.evaluation.problems import EvalProblem
from ttompc.evaluation.report_files import claim_report
from ttompc.evaluation.warmstart import default_workers
from ttompc.model_slots import MODEL_SLOTS
from ttompc.mpc.loop import MPCRun, run_mpc_batch
from ttompc.mpc.methods import ROBUST_BLEND, MethodInputs, methods_for
from ttompc.mpc.providers import full_horizon_plan
from ttompc.mpc.tto import check_rtg_scale
from ttompc.parallel import WorkerState, pool_map
from ttompc.progress import Bar, status
from ttompc.ranges import check_devices, setting
from ttompc.scenarios import get_scenario, scenario_spec
from ttompc.scenarios.base import Scenario

if TYPE_CHECKING:
    from ttompc.policy import Planner


@dataclass
class ClosedLoopConfig(Measurement):
    """``ttompc evaluate mpc`` settings (``key=value`` on the command line): a ``Measurement`` (protocol, overrides,
    problems, seed, horizons, plants, the perturbed plant, max_steps), by default on both plants, and the methods
    and workers that measure it."""

    plants: list[str] = setting(factory=lambda: list(PLANTS), nonempty=True, unique=True)
    model: str | None = None  # TTO model: zoo name, hf://ORG/NAME[@REV], bundle folder or .ckpt; None: baselines only
    ft_model: str | None = None  # FT-TTO model, same forms
    scenario: str | None = None  # default: the model's scenario
    # target blend of the R-TTO-MPC variants (docs/evaluation.md); 0: left out
    robust_blend: float = setting(ROBUST_BLEND, ge=0, lt=1)
    # rtg_0 = −rtg_scale·J_REL; None: the model's own (Planner.rtg_scale); its range: check_rtg_scale
    rtg_scale: float | None = setting(None)
    batch: int = setting(10, ge=1)  # problems per pool task, their episodes in lockstep (one batched rollout per step)
    workers: int = setting(0, ge=0, per_core=4, meaning="0: one per CPU core")  # processes
    device: str = setting("cpu", device="torch")
    out: str = ""  # default: outputs/evaluate/mpc-<scenario>

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.rtg_scale is not None:
            check_rtg_scale(self.rtg_scale)


def run_problems(
    scenario: Scenario,
    eps: Sequence[EvalProblem],
    models: dict[str, Planner],
    cfg: ClosedLoopConfig,
    on_episode: Callable[[], None] | None = None,
    *,
    runs: Sequence[tuple[str, MPCRun]] | None = None,
    plans: Sequence[Any] | None = None,
) -> list[dict[str, Any]]:
    """Every (plant, H, method) episode of the problems ``eps`` under the measurement ``cfg`` (or only the
    (plant, how it runs) of ``runs``) with ``models`` in their slots (``MODEL_SLOTS``), the episodes of one method in
    lockstep: their records, per problem, then plant, H and method. ``plans``: the problems' full-horizon plans
    (PLAN-ONCE's and ORACLE-MPC's; default: solved here). ``on_episode`` is called after each episode (a progress
    bar's ticker)."""
    records: list[dict[str, Any]] = []
    s = cfg.settings
    plans = list(plans) if plans is not None else [full_horizon_plan(scenario, ep.problem, s.backend) for ep in eps]
    starts = [ep.start for ep in eps]
    for _, run in cfg.runs(scenario) if runs is None else runs:  # the plant is in each episode's record
        for method in methods_for(models, cfg.robust_blend):
            inputs = MethodInputs(s, plans, models.get(method.model or ""), cfg.robust_blend, cfg.rtg_scale)
            episodes = run_mpc_batch(scenario, starts, method.providers(inputs), run)
            for ep, e in zip(eps, episodes, strict=True):
                records.append({"problem": ep.index, "seed": ep.seed, "ctg0": ep.ctg0, **episode_record(e)})
                if on_episode is not None:
                    on_episode()
    records.sort(key=lambda r: r["problem"])  # stable: plant, H and method order within a problem
    return records


def model_sources(cfg: ClosedLoopConfig) -> dict[str, str]:
    """The models ``cfg`` names, by model slot (``MODEL_SLOTS``: ``model`` in TTO's, ``ft_model`` in FT-TTO's)."""
    return {slot: getattr(cfg, key) for slot, key in MODEL_SLOTS.items() if getattr(cfg, key)}


def episodes_per_problem(cfg: ClosedLoopConfig, models: Collection[str]) -> int:
    """How many episodes ``run_problems`` runs per problem with the model slots ``models`` filled: every plant,
    horizon and method of ``methods_for``."""
    return len(cfg.plants) * len(cfg.horizons) * len(methods_for(models, cfg.robust_blend))


@dataclass
class _Worker:
    """What ``_init`` loads once per pool worker for ``_run``, and the problems and plans it has built so far."""

    cfg: ClosedLoopConfig
    scenario: Scenario
    models: dict[str, Planner]
    tick: Callable[[], None]
    problems: dict[int, tuple[EvalProblem, Any]] = field(default_factory=dict)


_WORKER: WorkerState[_Worker] = WorkerState()


def _init(cfg: dict[str, Any], tick: Callable[[], None]) -> None:
    from ttompc.config import from_container
    from ttompc.policy import Planner

    c = from_container(ClosedLoopConfig, cfg)
    assert c.scenario is not None  # the caller resolved it before starting the workers
    scenario = get_scenario(c.scenario)
    models = {slot: Planner.from_pretrained(src, scenario, device=c.device) for slot, src in model_sources(c).items()}
    _WORKER.set(_Worker(c, scenario, models, tick))


Task = tuple[tuple[int, ...], str, int]  # (problem indices, plant, horizon): the episodes of one lockstep batch


def _run(task: Task) -> list[dict[str, Any]]:
    w = _WORKER.get()
    cfg, sc = w.cfg, w.scenario
    indices, plant, horizon = task
    for ep in cfg.problem_set(sc, [i for i in indices if i not in w.problems]):  # each problem once per worker
        w.problems[ep.index] = (ep, full_horizon_plan(sc, ep.problem, cfg.settings.backend))
    eps, plans = zip(*(w.problems[i] for i in indices), strict=True)
    runs = [(p, run) for p, run in cfg.runs(sc) if p == plant and run.horizon == horizon]
    return run_problems(sc, eps, w.models, cfg, w.tick, runs=runs, plans=plans)


def tasks(problems: int, batch: int) -> list[tuple[int, ...]]:
    """Problem indices 0..problems-1 in pool tasks of ``batch`` (the last one shorter)."""
    return [tuple(range(i, min(i + batch, problems))) for i in range(0, problems, batch)]


def sweep_tasks(cfg: ClosedLoopConfig) -> list[Task]:
    """The sweep's pool tasks: each batch of ``tasks`` on each plant at each horizon, in that order."""
    return [(chunk, plant, H) for chunk in tasks(cfg.problems, cfg.batch) for plant in cfg.plants for H in cfg.horizons]


def sweep_fingerprint(cfg: ClosedLoopConfig, sc: Scenario) -> dict[str, Any]:
    """What decides the sweep's episodes (``episode_store.fingerprint``): its config, the resolved settings and
    perturbed plant, the scenario's version."""
    resolved = {"settings": asdict(cfg.settings), "plant": asdict(cfg.plant.resolve(sc)), "scenario": sc.version}
    return fingerprint(asdict(cfg), resolved)


def _pending(cfg: ClosedLoopConfig, store: EpisodeStore) -> tuple[list[Task], int]:
    """The tasks not yet done in ``store`` (a task is done when each of its problems has every method's episode on
    its plant at its horizon) and how many episodes of the sweep the other tasks hold (what the progress bar starts
    at: a task run again counts all its episodes)."""
    methods = len(methods_for(model_sources(cfg), cfg.robust_blend))
    count = Counter((p, plant, H) for p, plant, H, _ in store.done)
    every = sweep_tasks(cfg)
    todo = [t for t in every if any(count[(p, t[1], t[2])] < methods for p in t[0])]
    return todo, methods * (sum(len(t[0]) for t in every) - sum(len(t[0]) for t in todo))


def sweep_records(cfg: ClosedLoopConfig, store: EpisodeStore) -> list[dict[str, Any]]:
    """The stored episodes of the sweep's grid in report order: by problem, then plant and horizon in the config's
    order, then method in the order they ran."""
    plants, horizons = {p: i for i, p in enumerate(cfg.plants)}, {h: i for i, h in enumerate(cfg.horizons)}
    mine = [r for (p, plant, H, _), r in store.done.items() if p < cfg.problems and plant in plants and H in horizons]
    return sorted(mine, key=lambda r: (r["problem"], plants[r["plant"]], horizons[r["horizon"]]))


def run_closed_loop(cfg: ClosedLoopConfig) -> dict[str, Any]:
    """Run the study as a resumable sweep into ``cfg.out`` (default ``outputs/evaluate/mpc-<scenario>``), a folder
    claimed before any work (``report_files.claim_report``: new, empty or a closed-loop report's, else a one-line
    ``UserError``): each task's episodes are stored as it finishes (``EpisodeStore``), the episodes a previous run
    of the same configuration stored there are not run again, and a progress bar counts the sweep's episodes with
    an ETA. Then writes ``mpc.json`` (last, marked complete), ``mpc.md`` (the table), ``mpc_runs.csv`` and plots
    into it (``closed_loop_report.write_report``)."""
    from ttompc.config import to_container

    if cfg.scenario is None:
        raise ValueError("ClosedLoopConfig.scenario is not set (the command takes it from the model)")
    check_devices(cfg)  # its device and workers exist here, as ``ttompc evaluate mpc`` checks them
    sc = get_scenario(cfg.scenario)
    too_long = sorted({h for h in cfg.horizons if h > sc.n_steps})
    if too_long:  # refused, not clipped: a clipped horizon would report under a number that was never run
        raise UserError(
            f"horizons {too_long} exceed the horizon of {sc.name}, N = {sc.n_steps} steps",
            f"pass horizons of at most {sc.n_steps} (horizons=[{sc.n_steps}] plans the whole remaining episode)",
        )
    cfg.horizons = sorted(set(cfg.horizons))
    out = claim_report(cfg.out or f"outputs/evaluate/mpc-{sc.name}", "mpc")
    workers = default_workers(cfg.workers)
    t0, load = time.perf_counter(), load_average()
    store = EpisodeStore.open(out, sweep_fingerprint(cfg, sc))
    todo, done = _pending(cfg, store)
    total = cfg.problems * episodes_per_problem(cfg, model_sources(cfg))
    if done:
        status(f"ttompc evaluate mpc: resuming the sweep in {out}: {done} of {total} episodes done")
    with Bar(total, f"mpc {sc.name}", "episode", initial=done) as bar:
        init = (to_container(cfg), bar.ticker())
        for rs in pool_map(_run, todo, workers, _init, init, scenarios=[scenario_spec(sc)]):
            store.add(rs)
    return write_report(cfg, sc, sweep_records(cfg, store), out, workers, t0, load)
