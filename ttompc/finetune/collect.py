"""DAgger data collection (paper Alg. 1, §IV-C): closed-loop rollouts labelled by the expert.

A rollout runs one episode in which the exploration policy alternates between the learner (TTO-MPC with the current
model, H drawn per rollout from ``exploration.horizons``) and the expert (full-horizon SCP over [t, N) from the true
state) in expert windows (``exploration``; by default 1–3 windows of 15–25 steps, one covering the end). The expert
solves at the labelled steps (``labels``: every step, the paper, or ``labels.per_rollout`` drawn ones, tilted toward
late steps by ``labels.late``) and wherever it acts, each time from REL over [t, N) from x_t, as a from-scratch solve
does (REL at t = 0); where the expert acts on consecutive steps its own converged plan's tail is reused when the
state is on it (plan reuse, ``ttompc.mpc.loop``).
Warm-starting it from its previous plan shifted by one step instead (the reference's expert) lands in worse local
optima (measured in docs/scaling.md, "Label cost").

Labels (``labels.kind``):
* ``step`` (the paper): a labelled x_t gets the expert's control u*_t and the state *that control* leads to with the
  exact dynamics, x*_{t+1} = f(x_t, u*_t). The reference paired the expert's planned next state with the *executed*
  action token; our (target_action, target_next_state) pair is always consistent. One row per rollout: the visited
  states, executed actions and the learner's running conditioning, NaN targets at unlabelled steps (no loss).
* ``plan`` (a departure): one row per labelled step t whose expert solve converged: the visited prefix, then the
  expert's plan from x_t, with targets from t on (``rows.plan_row``). TTO-MPC's terminal target is the model's H-step
  rollout from the visited history; these rows supervise exactly that rollout. Their costates (the value's gradient
  targets) are those of the expert's solve from x_t at steps t+1..N (a reused plan's: those of the solve that
  produced it, shifted; ``Expert.plan_costates``), NaN before, where the backend gives none and where the plan
  misses the goal (``ExpertController``). The expert is ``ttompc.mpc.expert``.
The solver columns hold the row's cost, the learner's/expert's compute time (solve_time/solver_time), the keep-out
violations of the row's trajectory (violation) and "H=..;expert_steps=..;fallbacks=..;plant=..;labels=.." (status;
plan rows add ";plan_from=t"). Rollouts are kept whether or not they end feasible: their visited states are where
the learner needs corrections.

Seeds: rollout (i, r) draws everything (problem, H, windows) from ``ttompc.seeding.rollout_seed(seed, i, r)``, never
the wall clock. Rows go through the same resumable writer as open-loop generation (``ShardedFolder``, shard k =
rollouts [k·S, (k+1)·S), ``source="dagger"``, ``iteration=i``) into ``<run>/dagger/iter-<i>/``, which the DataModule
reads like an open-loop folder; each rank collects its own shards with the shared process pool. A worker runs
``collect.batch`` rollouts of one shard in lockstep (``collect_rollouts``) through the MPC loop (``run_mpc_batch``:
the learners are its episodes, sharing one batched transformer context; the expert is a ``StepHook`` beside them).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ttompc.data.config import SplitConfig
from ttompc.data.distributed import RankInfo
from ttompc.data.generate import split_of
from ttompc.data.resumable import ShardedFolder
from ttompc.data.schema import trajectory_features
from ttompc.evaluation.problems import first_solvable
from ttompc.finetune.config import DaggerConfig, ExplorationConfig, LabelConfig, check_rollout_settings
from ttompc.finetune.rows import plan_row, trajectory_row
from ttompc.mpc.episode import Episode
from ttompc.mpc.expert import Expert, ExpertRollout
from ttompc.mpc.loop import EpisodeStart, MPCRun, run_mpc_batch
from ttompc.mpc.methods import MethodInputs, model_method
from ttompc.mpc.plant import PLANT_STREAM, Plant, PlantNoise
from ttompc.mpc.providers import Provider
from ttompc.mpc.settings import MPCSettings
from ttompc.mpc.tto import TTOProvider
from ttompc.parallel import WorkerState, pool_map
from ttompc.progress import Bar
from ttompc.scenarios import get_scenario, scenario_spec
from ttompc.scenarios.base import Problem, Scenario
from ttompc.seeding import rng as seeded_rng
from ttompc.seeding import rollout_seed

if TYPE_CHECKING:
    from ttompc.policy import Planner, RolloutContext

ITERATION_IDS = 10_000_000  # rollout r of iteration i has problem id i·ITERATION_IDS + r


def rollout_id(iteration: int, index: int) -> int:
    """Problem id of a rollout, unique across iterations."""
    return iteration * ITERATION_IDS + index


def expert_schedule(rng: np.random.Generator, n_steps: int, cfg: ExplorationConfig) -> np.ndarray:
    """Steps (N,) bool where the expert acts: U{windows} windows of U{window_length} steps (clipped to N); with
    ``end_window`` the first one ends at the last step and starts within [N − w, N − 11] like the reference."""
    mask = np.zeros(n_steps, dtype=bool)
    n_windows = int(rng.integers(cfg.windows[0], cfg.windows[1] + 1))
    for j in range(n_windows):
        w = min(int(rng.integers(cfg.window_length[0], cfg.window_length[1] + 1)), n_steps)
        if w == 0:
            continue
        if j == 0 and cfg.end_window:
            start = int(rng.integers(n_steps - w, max(n_steps - w, n_steps - 11) + 1))
            mask[start:] = True
        else:
            start = int(rng.integers(0, n_steps - w + 1))
            mask[start : start + w] = True
    return mask


def _sample_problem(scenario: Scenario, rng: np.random.Generator, attempts: int = 100) -> tuple[Problem, Any]:
    """A valid problem whose REL solves (its cost conditions the learner: rtg_0 = −J_REL)."""
    found = first_solvable(scenario, (scenario.sample(rng) for _ in range(attempts)))
    if found is None:
        raise RuntimeError(f"{scenario.name}: no valid problem with a REL solution in {attempts} draws")
    return found[1], found[2]


def label_schedule(rng: np.random.Generator, n_steps: int, per_rollout: int, late: float = 0.0) -> np.ndarray:
    """Steps (N,) bool that get an expert label: ``per_rollout`` distinct steps drawn without replacement with
    weights exp(late · t/(N − 1)) (0: uniform; 2: the last step ~7× as likely as the first), or every step when
    ``per_rollout`` is 0 or >= N (the paper). Draws nothing from ``rng`` when every step is labelled, so such
    rollouts keep their seeds."""
    if per_rollout <= 0 or per_rollout >= n_steps:
        return np.ones(n_steps, dtype=bool)
    weights = None
    if late:
        w = np.exp(late * np.arange(n_steps) / max(n_steps - 1, 1))
        weights = w / w.sum()
    mask = np.zeros(n_steps, dtype=bool)
    mask[rng.choice(n_steps, size=per_rollout, replace=False, p=weights)] = True
    return mask


def collect_rollout(
    scenario: Scenario,
    planner: Planner,
    iteration: int,
    index: int,
    root_seed: int,
    exploration: ExplorationConfig,
    labels: LabelConfig | None = None,
    *,
    settings: MPCSettings | None = None,
    perturbed: float = 0.0,
    robust_blend: float = 0.0,
) -> list[dict[str, Any]]:
    """One DAgger rollout -> its schema rows: ``collect_rollouts`` for one index."""
    return collect_rollouts(
        scenario,
        planner,
        iteration,
        [index],
        root_seed,
        exploration,
        labels,
        settings=settings,
        perturbed=perturbed,
        robust_blend=robust_blend,
    )[0]


def rollout_plant(scenario: Scenario, seed: int, perturbed: float) -> Plant:
    """The plant of the rollout seeded ``seed``: the evaluations' perturbed plant (``PlantNoise.perturbed``) with
    probability ``perturbed``, else the exact dynamics; the draw and the disturbances come from the rollout's seed
    on streams of their own (a share of 0 draws nothing), so the problem, horizon and windows stay the same."""
    on_perturbed = perturbed > 0 and bool(seeded_rng(seed, PLANT_STREAM, 1).random() < perturbed)
    plant = Plant(scenario, PlantNoise.perturbed(scenario) if on_perturbed else None)
    plant.reset(seed)
    return plant


def collect_rollouts(
    scenario: Scenario,
    planner: Planner,
    iteration: int,
    indices: Sequence[int],
    root_seed: int,
    exploration: ExplorationConfig,
    labels: LabelConfig | None = None,
    *,
    settings: MPCSettings | None = None,
    perturbed: float = 0.0,
    robust_blend: float = 0.0,
) -> list[list[dict[str, Any]]]:
    """The DAgger rollouts ``indices`` of ``iteration``, run in lockstep -> each one's schema rows (see the module
    docstring for the labels): one row with ``kind="step"`` labels, one row per labelled step with ``kind="plan"``.
    The learners are TTO-MPC (``METHODS``; R-TTO-MPC with the target blend ``robust_blend`` > 0) at each rollout's H,
    the episodes of ``run_mpc_batch``, and share one batched transformer context (``RolloutGroup``: one batched
    rollout per step), so a rollout's learner plans equal its lone run's up to the rounding of the batch; the expert
    acts beside them (``Expert``). Both controllers run under ``settings`` (default: the paper's), which
    ``check_rollout_settings`` refuses where the rollouts cannot honour them (a decode schedule, a terminal term or
    rtg mode they cannot run): mode, backend and plan reuse (without reuse the labels are the same) for both; for the
    learner (its H drawn by the exploration, Alg. 1) also the end horizon, the terminal term with its tracking
    weight, the rtg mode (the one its model runs, ``ttompc.mpc.rtg``) and real-time iteration (a full solve after the
    expert acted, as after any step whose executed control was not its plan's). The expert's windows always reach
    the end, where those three do not apply, and always converge (its labels are optima, whatever ``rti`` says). A
    share ``perturbed`` of the rollouts runs on the perturbed plant (``rollout_plant``): both controllers plan from
    its measured states, the expert labels them."""
    labels = labels or LabelConfig()
    s = settings or MPCSettings()
    check_rollout_settings(s)
    if not indices:
        return []
    method = model_method("TTO", robust_blend > 0)
    learners = _tto(method.providers(MethodInputs(s, [None] * len(indices), planner, robust_blend)))
    rollouts, starts = [], []
    for index in indices:
        seed = rollout_seed(root_seed, iteration, index)
        rng = np.random.default_rng(seed)
        problem, rel = _sample_problem(scenario, rng)
        N = problem.n_steps
        H = min(int(rng.choice(exploration.horizons)), N)
        expert_steps = expert_schedule(rng, N, exploration)
        labelled = label_schedule(rng, N, labels.per_rollout, labels.late)
        plant = rollout_plant(scenario, seed, perturbed).noise
        rollouts.append(ExpertRollout.start(scenario, (index, seed, problem, rel, H), expert_steps, labelled, plant, s))
        starts.append(EpisodeStart(problem, rel.cost, seed, horizon=H, plant=plant))
    if len({r.problem.n_steps for r in rollouts}) > 1:
        raise ValueError("rollouts run in lockstep need problems of one length N")
    group = learners[0].group  # the learners', made together (``Method.providers``)
    run = MPCRun(max(r.H for r in rollouts), s)  # each rollout plans at its own H (EpisodeStart.horizon)
    episodes = run_mpc_batch(scenario, starts, learners, run, hook=Expert(scenario, rollouts, group, s.backend))
    return [
        _rows(scenario, r, e, learner.slot, iteration, labels, group.context)
        for r, e, learner in zip(rollouts, episodes, learners, strict=True)
    ]


def _tto(providers: Sequence[Provider]) -> list[TTOProvider]:
    """TTO-MPC's providers, as the TTO providers they are."""
    out = [p for p in providers if isinstance(p, TTOProvider)]
    if len(out) != len(providers):
        raise TypeError("DAgger's learners are TTO-MPC providers")
    return out


def _rows(
    scenario: Scenario,
    r: ExpertRollout,
    episode: Episode,
    slot: int,
    iteration: int,
    labels: LabelConfig,
    ctx: RolloutContext | None,
) -> list[dict[str, Any]]:
    """A finished rollout's schema rows (``labels.kind``) from its learner's ``episode``: its rtg/ctg from row ``slot``
    of the learners' context, the learner's time and fallbacks from the steps it acted in."""
    problem, N = r.problem, r.problem.n_steps
    Xa, Ua = episode.X, episode.U
    assert ctx is not None
    rtg, ctg = ctx.rtg[slot, :N].double().cpu().numpy(), ctx.ctg[slot, :N].double().cpu().numpy()
    learned = ~r.expert_steps[: len(Ua)]
    learner_time = float(np.sum(episode.warm_times[learned] + episode.solve_times[learned]))
    fallbacks = episode.fallbacks - sum(e.fallback for t, e in r.plans.items() if r.expert_steps[t])
    common = dict(
        problem_id=rollout_id(iteration, r.index),
        seed=r.seed,
        source="dagger",
        iteration=iteration,
        solve_time=learner_time,
        solver_time=r.expert_time,
    )
    n_expert, n_labels = int(r.expert_steps.sum()), int(r.labelled.sum())
    plant = "nominal" if r.plant.nominal else "perturbed"
    status = f"H={r.H};expert_steps={n_expert};fallbacks={fallbacks};plant={plant};labels={n_labels}"
    if labels.kind == "plan":
        return [
            plan_row(scenario, problem, Xa, Ua, rtg, ctg, t, e, r.costates[t], status, common, labels.rtg)
            for t, e in sorted(r.plans.items())
            if not e.fallback
        ]
    m, n = scenario.control_dim, scenario.state_dim
    target_actions = np.full((N, m), np.nan)
    target_next = np.full((N, n), np.nan)
    for t, e in r.plans.items():
        target_actions[t] = e.u
        x_star = scenario.step(problem, t, Xa[t], e.u)
        target_next[t] = scenario.to_model_states(problem, x_star[None], start=t + 1)[0]
    S = scenario.to_model_states(problem, Xa)
    return [trajectory_row(scenario, problem, Xa, Ua, S, rtg, ctg, target_actions, target_next, status, common)]


# ------------------------------------------------------------------------------------------------ collection
def rollout_folder(folder: str | Path, scenario: Scenario, rollouts: int, shard_size: int) -> ShardedFolder:
    """The shards of one iteration's rollouts (files ``<split>/dagger-<k>.parquet``)."""
    return ShardedFolder(folder, trajectory_features(scenario), rollouts, shard_size, prefix="dagger")


@dataclass
class _Collector:
    """What ``_init_collector`` loads once per pool worker for ``_collect_chunk``."""

    scenario: Scenario
    planner: Planner
    cfg: DaggerConfig


_COLLECTOR: WorkerState[_Collector] = WorkerState()


def _init_collector(scenario_name: str, planner_dir: str, cfg: DaggerConfig) -> None:
    """Runs once per worker: the scenario (its module is imported by the pool) and the planner, loaded once."""
    from ttompc.policy import Planner

    scenario = get_scenario(scenario_name)
    _COLLECTOR.set(_Collector(scenario, Planner.from_pretrained(planner_dir, scenario), cfg))


def _collect_chunk(task: tuple[int, list[int]]) -> list[list[dict[str, Any]]]:
    iteration, indices = task
    w = _COLLECTOR.get()
    cfg = w.cfg
    return collect_rollouts(
        w.scenario,
        w.planner,
        iteration,
        indices,
        cfg.seed,
        cfg.exploration,
        cfg.labels,
        settings=cfg.eval.settings,
        perturbed=cfg.collect.perturbed,
        robust_blend=cfg.eval.robust_blend,
    )


def chunks(folder: ShardedFolder, shards: Sequence[int], batch: int) -> list[list[int]]:
    """The rollout indices of ``shards`` cut into runs of at most ``batch`` that never cross a shard (a shard is
    written as soon as its chunks are back)."""
    out = []
    for k in shards:
        items = folder.items([k])
        out += [items[i : i + batch] for i in range(0, len(items), batch)]
    return out


def collect_iteration(
    cfg: DaggerConfig, scenario: Scenario, iteration: int, planner_dir: Path, folder: ShardedFolder, ranks: RankInfo
) -> list[int]:
    """Collect this rank's missing shards of iteration ``iteration`` with the planner in ``planner_dir``; returns
    the shards written (done shards are skipped: an interrupted collection resumes without recollecting)."""
    todo = folder.pending(ranks)
    tasks = [(iteration, chunk) for chunk in chunks(folder, todo, cfg.collect.batch)]
    workers = cfg.collect.workers or os.cpu_count() or 1
    splits = SplitConfig(train=1.0 - cfg.collect.val_fraction, val=cfg.collect.val_fraction, test=0.0, salt=iteration)
    init = (scenario.name, str(planner_dir), cfg)
    results = pool_map(_collect_chunk, tasks, workers, _init_collector, init, scenarios=[scenario_spec(scenario)])
    rows = (rollout for chunk in results for rollout in chunk)
    with Bar(sum(len(c) for _, c in tasks), f"collect iteration {iteration}", "rollout") as bar:
        for k, rollouts, seconds in folder.group(todo, bar.each(rows)):
            shard_rows = [row for rollout in rollouts for row in rollout]
            by_split: dict[str, list[dict[str, Any]]] = {"train": [], "val": []}
            for row in shard_rows:
                by_split[split_of(row["problem_id"] % ITERATION_IDS, splits)].append(row)
            folder.write(
                k,
                by_split,
                iteration=iteration,
                rollouts=len(rollouts),
                rows=len(shard_rows),
                mean_cost=float(np.mean([r["cost"] for r in shard_rows])),
                seconds=seconds,
            )
    return todo
