"""DAgger data collection (paper Alg. 1, §IV-C): closed-loop rollouts labelled by the expert.

A rollout runs one episode in which the exploration policy alternates between the learner (TTO-MPC with the current
model, H drawn per rollout from ``exploration.horizons``) and the expert (full-horizon SCP over [t, N) from the true
state) in expert windows (``exploration``; by default 1–3 windows of 15–25 steps, one covering the end). The expert
solves at the labelled steps (``labels``: every step, the paper, or ``labels.per_rollout`` drawn ones) and wherever it
acts, each time from REL over [t, N) from x_t, as a from-scratch solve does (REL at t = 0); where the expert acts on
consecutive steps its own converged plan's tail is reused when the state is on it (plan reuse, ``ttompc.mpc.loop``).
Warm-starting it from its previous plan shifted by one step instead (the reference's expert) was measured to land in
worse local optima: 3.6% costlier than from scratch at a visited state of the short free-flyer (docs/scaling.md).

Labels (``labels.kind``):
* ``step`` (the paper): a labelled x_t gets the expert's control u*_t and the state *that control* leads to with the
  exact dynamics, x*_{t+1} = f(x_t, u*_t). The reference paired the expert's planned next state with the *executed*
  action token; our (target_action, target_next_state) pair is always consistent. One row per rollout: the visited
  states, executed actions and the learner's running conditioning, NaN targets at unlabelled steps (no loss).
* ``plan`` (a departure): one row per labelled step t whose expert solve converged: the visited prefix, then the
  expert's plan from x_t, with targets from t on (``_plan_row``). TTO-MPC's terminal target is the model's H-step
  rollout from the visited history; these rows supervise exactly that rollout.
The solver columns hold the row's cost, the learner's/expert's compute time (solve_time/solver_time), the keep-out
violations of the row's trajectory (violation) and "H=..;expert_steps=..;fallbacks=..;labels=.." (status; plan rows
add ";plan_from=t"). Rollouts are kept whether or not they end feasible: their visited states are where the learner
needs corrections.

Seeds: rollout (i, r) draws everything (problem, H, windows) from ``ttompc.seeding.rollout_seed(seed, i, r)``, never
the wall clock. Rows go through the same resumable writer as open-loop generation (``ShardedFolder``, shard k =
rollouts [k·S, (k+1)·S), ``source="dagger"``, ``iteration=i``) into ``<run>/dagger/iter-<i>/``, which the DataModule
reads like an open-loop folder; each rank collects its own shards with the shared process pool.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from ttompc.data.config import SplitConfig
from ttompc.data.distributed import RankInfo
from ttompc.data.generate import split_of
from ttompc.data.resumable import ShardedFolder
from ttompc.data.schema import make_row, trajectory_features
from ttompc.evaluation.problems import first_solvable
from ttompc.finetune.config import DaggerConfig, ExplorationConfig, LabelConfig
from ttompc.mpc.loop import MPCController, StepPlan
from ttompc.mpc.providers import ShiftProvider
from ttompc.mpc.settings import MPCSettings
from ttompc.mpc.tto import TTOProvider
from ttompc.parallel import pool_map
from ttompc.progress import Bar
from ttompc.scenarios import get_scenario, scenario_spec
from ttompc.scenarios.base import Problem, Scenario, Window
from ttompc.seeding import rollout_seed
from ttompc.solvers.scp import solve_rel

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


def label_schedule(rng: np.random.Generator, n_steps: int, per_rollout: int) -> np.ndarray:
    """Steps (N,) bool that get an expert label: ``per_rollout`` distinct steps drawn uniformly (0 or >= N: every
    step, the paper). Draws nothing from ``rng`` when every step is labelled, so such rollouts keep their seeds."""
    if per_rollout <= 0 or per_rollout >= n_steps:
        return np.ones(n_steps, dtype=bool)
    mask = np.zeros(n_steps, dtype=bool)
    mask[rng.choice(n_steps, size=per_rollout, replace=False)] = True
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
) -> list[dict[str, Any]]:
    """One DAgger rollout -> its schema rows (see the module docstring for the labels): one row with ``kind="step"``
    labels, one row per labelled step with ``kind="plan"``. From ``settings`` both controllers take mode, backend and
    plan reuse (without reuse the labels are the same); the learner runs the paper's fixed H (exploration, Alg. 1)."""
    labels = labels or LabelConfig()
    s = settings or MPCSettings()
    loop = MPCSettings(mode=s.mode, backend=s.backend, reuse=s.reuse)
    seed = rollout_seed(root_seed, iteration, index)
    rng = np.random.default_rng(seed)
    problem, rel = _sample_problem(scenario, rng)
    N = problem.n_steps
    H = min(int(rng.choice(exploration.horizons)), N)
    expert_steps = expert_schedule(rng, N, exploration)
    labelled = label_schedule(rng, N, labels.per_rollout) | expert_steps
    learner_provider = TTOProvider(planner)
    learner = MPCController(scenario, problem, learner_provider, H, loop)
    shift = ShiftProvider()
    expert = MPCController(scenario, problem, shift, N, loop)
    learner_provider.reset(scenario, problem, rel.cost)
    shift.reset(scenario, problem, rel.cost)
    x = problem.x0.copy()
    X, U = [x], []
    plans: dict[int, StepPlan] = {}  # the expert's plan at each labelled step
    learner_time = expert_time = 0.0
    fallbacks = 0
    for t in range(N):
        e = None
        # the expert starts from REL over [t, N) from x_t, as a from-scratch solve does: REL from the straight line,
        # not warm-started by an earlier step's REL (which can stop at another point, and the label with it)
        if labelled[t]:
            t0 = time.perf_counter()
            rest = Window(t, N - t, N)
            start = rel if t == 0 else solve_rel(scenario, problem, window=rest, x_start=x, backend=loop.backend)
            shift.reset_plan(start.X, start.U)
            expert_time += time.perf_counter() - t0
            e = plans[t] = expert.plan(t, x)
            expert_time += e.warm_time + e.solve_time
        if expert_steps[t]:
            assert e is not None
            plan, u = e, e.u
        else:
            plan = learner.plan(t, x)
            learner_time += plan.warm_time + plan.solve_time
            fallbacks += plan.fallback
            u = plan.u
        x_next = scenario.step(problem, t, x, u)
        if e is not None:
            expert.observe(e, u, x_next)
        learner.observe(plan, u, x_next)
        X.append(x_next)
        U.append(u)
        x = x_next
    Xa, Ua = np.stack(X), np.stack(U)
    ctx = learner_provider.context
    assert ctx is not None
    rtg, ctg = ctx.rtg[0, :N].double().cpu().numpy(), ctx.ctg[0, :N].double().cpu().numpy()
    common = dict(problem_id=rollout_id(iteration, index), seed=seed, source="dagger", iteration=iteration,
                  solve_time=learner_time, solver_time=expert_time)  # fmt: skip
    status = f"H={H};expert_steps={int(expert_steps.sum())};fallbacks={fallbacks};labels={int(labelled.sum())}"
    if labels.kind == "plan":
        return [
            _plan_row(scenario, problem, Xa, Ua, rtg, ctg, t, e, status, common, labels.rtg)
            for t, e in sorted(plans.items())
            if not e.fallback
        ]
    m, n = scenario.control_dim, scenario.state_dim
    target_actions = np.full((N, m), np.nan)
    target_next = np.full((N, n), np.nan)
    for t, e in plans.items():
        target_actions[t] = e.u
        x_star = scenario.step(problem, t, Xa[t], e.u)
        target_next[t] = scenario.to_model_states(problem, x_star[None], start=t + 1)[0]
    S = scenario.to_model_states(problem, Xa)
    return [_row(scenario, problem, Xa, Ua, S, rtg, ctg, target_actions, target_next, status, common)]


def _row(
    scenario: Scenario,
    problem: Problem,
    X: np.ndarray,
    U: np.ndarray,
    S: np.ndarray,
    rtg: np.ndarray,
    ctg: np.ndarray,
    target_actions: np.ndarray,
    target_next: np.ndarray,
    status: str,
    common: dict[str, Any],
) -> dict[str, Any]:
    """A DAgger row of the trajectory (X, U) with model states S: its cost and keep-out violations, the targets."""
    return make_row(
        scenario,
        problem,
        states=S,
        states_opt=X,
        actions=U,
        rtg=rtg,
        ctg=ctg,
        target_actions=target_actions,
        target_next_states=target_next,
        cost=scenario.cost(U),
        status=status,
        violation=float(np.sum(scenario.violations(problem, X))),
        **common,
    )


def _plan_row(
    scenario: Scenario,
    problem: Problem,
    X: np.ndarray,
    U: np.ndarray,
    rtg: np.ndarray,
    ctg: np.ndarray,
    t: int,
    e: StepPlan,
    status: str,
    common: dict[str, Any],
    rtg_label: Literal["learner", "expert"],
) -> dict[str, Any]:
    """The row of a ``plan`` label at step t: the visited prefix (states x_0..x_t, executed u_0..u_(t-1), the learner's
    rtg/ctg) followed by the expert's plan from x_t over [t, N); targets (the plan's controls and next states) from t
    on, NaN (no loss) before. From t the rtg is, with ``rtg="learner"``, the learner's value run on as the context
    runs it (rtg_(s+1) = rtg_s + c(u*_s)); with ``rtg="expert"`` the plan's own cost-to-go −Σ_(k>=s) c(u*_k), as in
    open-loop rows. The ctg is held (the expert plan is feasible)."""
    N = problem.n_steps
    Xr = np.concatenate([X[:t], e.X])  # (N+1, n)
    Ur = np.concatenate([U[:t], e.U])  # (N, m)
    S = scenario.to_model_states(problem, Xr)
    stage = scenario.stage_cost(e.U)  # (N - t,)
    if rtg_label == "expert":
        togo = -np.cumsum(stage[::-1])[::-1]
    else:
        togo = rtg[t] + np.concatenate([[0.0], np.cumsum(stage[:-1])])
    rtg_r = np.concatenate([rtg[:t], togo])
    ctg_r = np.concatenate([ctg[:t], np.full(N - t, ctg[t])])
    target_actions = np.full_like(Ur, np.nan)
    target_actions[t:] = e.U
    target_next = np.full((N, S.shape[1]), np.nan)
    target_next[t:] = S[t + 1 :]
    status = f"{status};plan_from={t}"
    return _row(scenario, problem, Xr, Ur, S, rtg_r, ctg_r, target_actions, target_next, status, common)


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


def _collect_one(task: tuple[int, int]) -> list[dict[str, Any]]:
    iteration, index = task
    cfg: DaggerConfig = _W["cfg"]
    return collect_rollout(
        _W["scenario"],
        _W["planner"],
        iteration,
        index,
        cfg.seed,
        cfg.exploration,
        cfg.labels,
        settings=cfg.settings(),
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
