"""DAgger data collection (paper Alg. 1, §IV-C): closed-loop rollouts labelled by the expert.

A rollout runs one episode in which the exploration policy alternates between the learner (TTO-MPC with the current
model, H drawn per rollout from ``exploration.horizons``) and the expert (full-horizon SCP over [t, N) from the true
state, warm-started by its own previous plan shifted one step; REL at t = 0) in expert windows (``exploration``; by
default 1–3 windows of 15–25 steps, one covering the end).

Labels: every visited state x_t gets the expert's control u*_t and the state *that control* leads to with the exact
dynamics, x*_{t+1} = f(x_t, u*_t). The reference paired the expert's planned next state with the *executed* action
token; our (target_action, target_next_state) pair is always consistent. The row's states, actions, rtg and ctg are
the visited states, executed actions and the learner's running conditioning; its solver columns hold the applied
cost, the learner's/expert's compute time (solve_time/solver_time), the keep-out violations of the executed
trajectory (violation) and "H=..;expert_steps=..;fallbacks=.." (status). Rollouts are kept whether or not they end
feasible: their visited states are where the learner needs corrections.

Seeds: rollout (i, r) draws everything (problem, H, windows) from ``ttompc.seeding.rollout_seed(seed, i, r)``, never
the wall clock. Rows go through the same resumable writer as open-loop generation (``ShardedFolder``, shard k =
rollouts [k·S, (k+1)·S), ``source="dagger"``, ``iteration=i``) into ``<run>/dagger/iter-<i>/``, which the DataModule
reads like an open-loop folder; each rank collects its own shards with the shared process pool.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ttompc.data.config import SplitConfig
from ttompc.data.distributed import RankInfo
from ttompc.data.generate import split_of
from ttompc.data.resumable import ShardedFolder
from ttompc.data.schema import make_row, trajectory_features
from ttompc.evaluation.problems import first_solvable
from ttompc.finetune.config import DaggerConfig, ExplorationConfig
from ttompc.mpc.loop import MPCController
from ttompc.mpc.providers import ShiftProvider
from ttompc.mpc.settings import MPCSettings
from ttompc.mpc.tto import TTOProvider
from ttompc.parallel import pool_map
from ttompc.progress import Bar
from ttompc.scenarios import get_scenario, scenario_spec
from ttompc.scenarios.base import Problem, Scenario
from ttompc.seeding import rollout_seed

if TYPE_CHECKING:
    from ttompc.policy import Planner

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


def collect_rollout(
    scenario: Scenario,
    planner: Planner,
    iteration: int,
    index: int,
    root_seed: int,
    exploration: ExplorationConfig,
    settings: MPCSettings | None = None,
) -> dict[str, Any]:
    """One DAgger rollout -> one schema row (see the module docstring for the labels). From ``settings`` both
    controllers take mode, backend and plan reuse (without reuse the labels are the same); the learner runs the
    paper's fixed H (exploration, Alg. 1)."""
    s = settings or MPCSettings()
    loop = MPCSettings(mode=s.mode, backend=s.backend, reuse=s.reuse)
    seed = rollout_seed(root_seed, iteration, index)
    rng = np.random.default_rng(seed)
    problem, rel = _sample_problem(scenario, rng)
    N = problem.n_steps
    H = min(int(rng.choice(exploration.horizons)), N)
    expert_steps = expert_schedule(rng, N, exploration)
    learner_provider = TTOProvider(planner)
    learner = MPCController(scenario, problem, learner_provider, H, loop)
    shift = ShiftProvider()
    expert = MPCController(scenario, problem, shift, N, loop)
    learner_provider.reset(scenario, problem, rel.cost)
    shift.reset(scenario, problem, rel.cost)
    shift.reset_plan(rel.X, rel.U)
    x = problem.x0.copy()
    X, U, U_star, X_star = [x], [], [], []
    learner_time = expert_time = 0.0
    fallbacks = 0
    for t in range(N):
        e = expert.plan(t, x)
        expert_time += e.warm_time + e.solve_time
        U_star.append(e.u)
        X_star.append(scenario.step(problem, t, x, e.u))
        if expert_steps[t]:
            plan, u = e, e.u
        else:
            plan = learner.plan(t, x)
            learner_time += plan.warm_time + plan.solve_time
            fallbacks += plan.fallback
            u = plan.u
        x_next = scenario.step(problem, t, x, u)
        expert.observe(e, u, x_next)
        learner.observe(plan, u, x_next)
        X.append(x_next)
        U.append(u)
        x = x_next
    Xa, Ua = np.stack(X), np.stack(U)
    ctx = learner_provider.context
    assert ctx is not None
    target_next = np.stack(
        [scenario.to_model_states(problem, X_star[t][None], start=t + 1)[0] for t in range(N)]
    )  # (N, n)
    return make_row(
        scenario,
        problem,
        problem_id=rollout_id(iteration, index),
        seed=seed,
        source="dagger",
        iteration=iteration,
        states=scenario.to_model_states(problem, Xa),
        states_opt=Xa,
        actions=Ua,
        rtg=ctx.rtg[0, :N].double().cpu().numpy(),
        ctg=ctx.ctg[0, :N].double().cpu().numpy(),
        target_actions=np.stack(U_star),
        target_next_states=target_next,
        cost=scenario.cost(Ua),
        status=f"H={H};expert_steps={int(expert_steps.sum())};fallbacks={fallbacks}",
        solve_time=learner_time,
        solver_time=expert_time,
        violation=float(np.sum(scenario.violations(problem, Xa))),
    )


# ------------------------------------------------------------------------------------------------ collection
def rollout_folder(folder: str | Path, scenario: Scenario, rollouts: int, shard_size: int) -> ShardedFolder:
    """The shards of one iteration's rollouts (files ``<split>/dagger-<k>.parquet``)."""
    return ShardedFolder(folder, trajectory_features(scenario), rollouts, shard_size, prefix="dagger")


_W: dict[str, Any] = {}


def _init_collector(scenario_name: str, planner_dir: str, cfg: DaggerConfig) -> None:
    """Runs once per worker: the scenario (its module is imported by the pool) and the planner, loaded once."""
    from ttompc.policy import Planner

    _W["scenario"] = scenario = get_scenario(scenario_name)
    _W["planner"] = Planner.from_pretrained(planner_dir, scenario)
    _W["cfg"] = cfg


def _collect_one(task: tuple[int, int]) -> dict[str, Any]:
    iteration, index = task
    cfg: DaggerConfig = _W["cfg"]
    return collect_rollout(
        _W["scenario"],
        _W["planner"],
        iteration,
        index,
        cfg.seed,
        cfg.exploration,
        cfg.settings(),
    )


def collect_iteration(
    cfg: DaggerConfig, scenario: Scenario, iteration: int, planner_dir: Path, folder: ShardedFolder, ranks: RankInfo
) -> list[int]:
    """Collect this rank's missing shards of iteration ``iteration`` with the planner in ``planner_dir``; returns
    the shards written (done shards are skipped: an interrupted collection resumes without recollecting)."""
    todo = folder.pending(ranks)
    tasks = [(iteration, r) for r in folder.items(todo)]
    workers = cfg.collect.workers or os.cpu_count() or 1
    splits = SplitConfig(train=1.0 - cfg.collect.val_fraction, val=cfg.collect.val_fraction, test=0.0, salt=iteration)
    init = (scenario.name, str(planner_dir), cfg)
    rows = pool_map(_collect_one, tasks, workers, _init_collector, init, scenarios=[scenario_spec(scenario)])
    with Bar(len(tasks), f"collect iteration {iteration}", "rollout") as bar:
        for k, shard_rows, seconds in folder.group(todo, bar.each(rows)):
            by_split: dict[str, list[dict[str, Any]]] = {"train": [], "val": []}
            for row in shard_rows:
                by_split[split_of(row["problem_id"] % ITERATION_IDS, splits)].append(row)
            folder.write(
                k,
                by_split,
                iteration=iteration,
                rollouts=len(shard_rows),
                mean_cost=float(np.mean([r["cost"] for r in shard_rows])),
                seconds=seconds,
            )
    return todo
