"""DAgger fine-tuning for MPC (paper Alg. 1, fact sheet §5.3).

Each iteration i:

1. **Collect** ``rollouts`` closed-loop episodes. The exploration policy alternates between the learner (TTO-MPC with
   the current model, H drawn per rollout from ``exploration.horizons``) and the expert (full-horizon SCP over
   [t, N) from the true state, warm-started by its own previous plan shifted one step; REL at t = 0) in expert
   windows (``exploration``; by default 1–3 windows of 15–25 steps, one covering the end).
2. **Label** every visited state x_t with the expert's control u*_t and the state *that control* leads to with the
   exact dynamics, x*_{t+1} = f(x_t, u*_t). The reference paired the expert's planned next state with the
   *executed* action token; our (target_action, target_next_state) pair is always consistent. The row's states,
   actions, rtg and ctg are the visited states, executed actions and the learner's running conditioning; its
   solver columns hold the applied cost, the learner's/expert's compute time (solve_time/solver_time), the keep-out
   violations of the executed trajectory (violation) and "H=..;expert_steps=..;fallbacks=.." (status). Rollouts
   are kept whether or not they end feasible: their visited states are where the learner needs corrections.
3. **Write** the rows as DAgger shards (``source="dagger"``, ``iteration=i``) through the dataset writer into
   ``<run>/dagger/iter-<i>/``; the DataModule mixes all DAgger folders so far with the open-loop data at
   ``data.open_loop_fraction`` ("fixed", the default; "grow" reproduces the reference's schedule).
4. **Train** ``steps_per_iteration`` more optimiser steps from the current weights (iteration 0: the pretrained
   model; later: resumed from the previous iteration's checkpoint, optimiser state included), export a Planner
   bundle and log closed-loop TTO-MPC metrics (also of the pretrained model, before iteration 0).

Seeds: rollout (i, r) draws everything (problem, H, windows) from ``SeedSequence(seed, spawn_key=(stream, i, r))``,
never the wall clock. Work split: shard k holds rollouts [k·S, (k+1)·S); under torchrun/SLURM rank r collects the
shards k ≡ r (mod world size), each with a spawn process pool. A shard counts as done when its metadata and
checksummed files exist, so an interrupted collection resumes without recollecting; ``<run>/dagger_state.json``
records finished iterations (checkpoint, planner, metrics) and a restart continues after the last one.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ttompc.config import to_container
from ttompc.data.config import SplitConfig
from ttompc.data.distributed import RankInfo, rank_info
from ttompc.data.generate import split_of
from ttompc.data.schema import make_row, trajectory_features
from ttompc.data.shards import ShardError, ShardWriter, atomic_write_json, verify_shard
from ttompc.evaluation.common import pool_map, scenario_module, worker_setup
from ttompc.finetune.config import ExplorationConfig, FinetuneConfig
from ttompc.mpc.loop import MPCController
from ttompc.mpc.providers import ShiftProvider, TTOProvider
from ttompc.scenarios import get_scenario
from ttompc.scenarios.base import Problem, Scenario

DAGGER_STREAM = 0x64616767  # "dagg": rollout seeds are disjoint from dataset and evaluation streams
STATE_FILE = "dagger_state.json"
SOURCE_PLANNER = "source-planner"


def rollout_seed(root: int, iteration: int, index: int) -> int:
    state = np.random.SeedSequence(root, spawn_key=(DAGGER_STREAM, iteration, index)).generate_state(1, np.uint64)
    return int(state[0] >> np.uint64(1))


def rollout_id(iteration: int, index: int) -> int:
    """Problem id of a rollout, unique across iterations."""
    return iteration * 10_000_000 + index


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
    from ttompc.evaluation.problems import first_solvable

    found = first_solvable(scenario, (scenario.sample(rng) for _ in range(attempts)))
    if found is None:
        raise RuntimeError(f"{scenario.name}: no valid problem with a REL solution in {attempts} draws")
    return found[1], found[2]


def collect_rollout(
    scenario: Scenario,
    planner: Any,
    iteration: int,
    index: int,
    root_seed: int,
    exploration: ExplorationConfig,
    *,
    mode: str = "soft",
    backend: str = "auto",
) -> dict[str, Any]:
    """One DAgger rollout -> one schema row (see the module docstring for the labels)."""
    seed = rollout_seed(root_seed, iteration, index)
    rng = np.random.default_rng(seed)
    problem, rel = _sample_problem(scenario, rng)
    N = problem.n_steps
    H = min(int(rng.choice(exploration.horizons)), N)
    expert_steps = expert_schedule(rng, N, exploration)
    learner_provider = TTOProvider(planner)
    learner = MPCController(scenario, problem, learner_provider, H, mode=mode, backend=backend)
    shift = ShiftProvider()
    expert = MPCController(scenario, problem, shift, N, mode=mode, backend=backend)
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
_W: dict[str, Any] = {}


def _init_collector(module: str, scenario_name: str, planner_dir: str, cfg: dict[str, Any]) -> None:
    from ttompc.policy import Planner

    worker_setup(module)
    _W["scenario"] = scenario = get_scenario(scenario_name)
    _W["planner"] = Planner.from_pretrained(planner_dir, scenario)
    _W["cfg"] = cfg


def _collect_one(task: tuple[int, int]) -> dict[str, Any]:
    iteration, index = task
    cfg = _W["cfg"]
    return collect_rollout(
        _W["scenario"],
        _W["planner"],
        iteration,
        index,
        cfg["seed"],
        ExplorationConfig(**cfg["exploration"]),
        mode=cfg["collect"]["mode"],
        backend=cfg["collect"]["backend"],
    )


def _shard_meta(folder: Path, k: int) -> Path:
    return folder / "meta" / f"shard-{k:05d}.json"


def shard_done(folder: Path, k: int) -> bool:
    path = _shard_meta(folder, k)
    if not path.is_file():
        return False
    try:
        for f in json.loads(path.read_text())["files"]:
            verify_shard(folder / f["path"], f["sha256"])
    except ShardError:
        return False
    return True


def collect_iteration(
    cfg: FinetuneConfig, scenario: Scenario, iteration: int, planner_dir: Path, folder: Path, ranks: RankInfo
) -> list[int]:
    """Collect this rank's missing shards of iteration ``iteration`` into ``folder``; returns the shards written."""
    c = cfg.dagger.collect
    S = c.shard_size
    n_shards = -(-c.rollouts // S)
    todo = [k for k in range(ranks.rank, n_shards, ranks.world_size) if not shard_done(folder, k)]
    if not todo:
        return []
    tasks = [(iteration, r) for k in todo for r in range(k * S, min((k + 1) * S, c.rollouts))]
    workers = min(c.workers or os.cpu_count() or 1, len(tasks))
    writer = ShardWriter(folder, trajectory_features(scenario), prefix="dagger")
    splits = SplitConfig(train=1.0 - c.val_fraction, val=c.val_fraction, test=0.0, salt=iteration)
    dcfg = to_container(cfg.dagger)
    init = (scenario_module(scenario.name), scenario.name, str(planner_dir), dcfg)
    buffer: list[dict[str, Any]] = []
    shards = iter(todo)
    k = next(shards)
    for row in pool_map(_collect_one, tasks, workers, _init_collector, init):
        buffer.append(row)
        if len(buffer) == min((k + 1) * S, c.rollouts) - k * S:
            _write_shard(folder, writer, k, buffer, splits, iteration)
            buffer, k = [], next(shards, -1)
    return todo


def _write_shard(
    folder: Path, writer: ShardWriter, k: int, rows: list[dict[str, Any]], splits: SplitConfig, iteration: int
) -> None:
    by_split: dict[str, list[dict[str, Any]]] = {"train": [], "val": []}
    for row in rows:
        by_split[split_of(row["problem_id"] % 10_000_000, splits)].append(row)
    files = [{"split": s, **writer.write(rs, k, s).to_dict()} for s, rs in by_split.items() if rs]
    meta = {
        "iteration": iteration,
        "shard": k,
        "rollouts": len(rows),
        "files": files,
        "mean_cost": float(np.mean([r["cost"] for r in rows])),
    }
    atomic_write_json(_shard_meta(folder, k), meta)


# ------------------------------------------------------------------------------------------------ training
@dataclass
class FinetuneResult:
    run_dir: Path
    iterations: list[dict[str, Any]]
    baseline_metrics: dict[str, float]


def _load_state(run: Path) -> dict[str, Any] | None:
    path = run / STATE_FILE
    return json.loads(path.read_text()) if path.is_file() else None


def _wait(predicate: Any, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"gave up waiting {timeout:.0f} s for {what}")
        time.sleep(2.0)


def _eval_problems(cfg: FinetuneConfig, scenario: Scenario) -> list[Any]:
    from ttompc.evaluation.problems import eval_problem

    e = cfg.dagger.eval
    return [eval_problem(scenario, e.seed, i, nonconvex_only=True) for i in range(e.problems)]


def _closed_loop(cfg: FinetuneConfig, planner: Any, problems: list[Any]) -> dict[str, float]:
    from ttompc.mpc.metrics import closed_loop_metrics
    from ttompc.parallel import single_torch_thread

    e = cfg.dagger.eval
    with single_torch_thread():
        metrics, _ = closed_loop_metrics(planner, problems, e.horizon, max_steps=e.max_steps)
    return metrics


def _train_iteration(
    cfg: FinetuneConfig,
    iteration: int,
    planner: Any,
    dagger_dirs: list[str],
    resume_from: Path | None,
    logger: Any,
    ckpt: Path,
) -> int:
    """Continue training for ``steps_per_iteration`` steps on open-loop + DAgger data; returns the global step."""
    from ttompc.data.datamodule import TrajectoryDataModule
    from ttompc.training.module import TrajectoryTransformerModule
    from ttompc.training.run import build_trainer
    from ttompc.version import code_version

    dm = TrajectoryDataModule(replace(cfg.data, dagger_dirs=dagger_dirs, seed=cfg.data.seed + iteration))
    dm.setup("fit")
    if dm.scenario_name != planner.scenario.name:
        raise ValueError(f"open-loop data is for {dm.scenario_name!r}, the model for {planner.scenario.name!r}")
    for key in ("states", "actions", "rtg", "ctg"):
        if not np.allclose(dm.stats.mean[key], planner.stats.mean[key], rtol=1e-4, atol=1e-6) or not np.allclose(
            dm.stats.std[key], planner.stats.std[key], rtol=1e-4, atol=1e-6
        ):
            raise ValueError(
                f"normalisation statistics of {cfg.data.paths} differ from the model's ({key}); fine-tune on the "
                "open-loop dataset the model was trained on"
            )
    module = TrajectoryTransformerModule(
        model_config=to_container(planner.model.cfg),
        optim=to_container(cfg.optim),
        scenario=planner.scenario.name,
        scenario_version=planner.scenario.version,
        norm_stats=planner.stats.to_dict(),
        recipe=to_container(cfg),
        code_version=code_version(),
        plot_trajectories=False,
    )
    if resume_from is None:
        module.model.load_state_dict(planner.model.state_dict())
    trainer = build_trainer(
        cfg.trainer,
        cfg.optim,
        Path(cfg.trainer.out_dir),
        logger,
        max_steps=(iteration + 1) * cfg.dagger.steps_per_iteration,
        enable_checkpointing=False,
    )
    trainer.fit(module, datamodule=dm, ckpt_path=str(resume_from) if resume_from else None)
    trainer.save_checkpoint(ckpt)
    return int(trainer.global_step)


def finetune(cfg: FinetuneConfig, source: str, ranks: RankInfo | None = None) -> FinetuneResult:
    """Run (or resume) DAgger fine-tuning of the model ``source`` (checkpoint, bundle dir or zoo name)."""
    import lightning as L

    from ttompc.policy import Planner
    from ttompc.training.loggers import build_logger

    ranks = ranks or rank_info()
    run = Path(cfg.trainer.out_dir)
    run.mkdir(parents=True, exist_ok=True)
    L.seed_everything(cfg.trainer.seed, workers=True)
    state = _load_state(run)
    if state is not None and state["source"] != str(source):
        raise ValueError(f"{run} fine-tunes {state['source']!r}, not {source!r}; use another trainer.out_dir")
    src_dir = run / SOURCE_PLANNER
    if ranks.is_main and not (src_dir / "config.json").is_file():
        Planner.from_pretrained(source).save(src_dir)
    _wait(lambda: (src_dir / "config.json").is_file(), cfg.dagger.collect.wait_s, "the source planner")
    source_planner = Planner.from_pretrained(src_dir)
    scenario = source_planner.scenario
    if state is None:
        state = {"source": str(source), "seed": cfg.dagger.seed, "completed": [], "baseline_metrics": None}
    recipe = to_container(cfg)
    logger = build_logger(cfg.logger, run, recipe) if ranks.is_main else None
    eval_problems = _eval_problems(cfg, scenario) if ranks.is_main else []
    if ranks.is_main and state["baseline_metrics"] is None:
        state["baseline_metrics"] = _closed_loop(cfg, source_planner, eval_problems)
        _log(logger, state["baseline_metrics"], -1, 0)
        atomic_write_json(run / STATE_FILE, state)
    n_shards = -(-cfg.dagger.collect.rollouts // cfg.dagger.collect.shard_size)
    for i in range(len(state["completed"]), cfg.dagger.iterations):
        prev = state["completed"][-1] if state["completed"] else None
        planner_dir = Path(prev["planner"]) if prev else src_dir
        folder = run / "dagger" / f"iter-{i:03d}"
        collect_iteration(cfg, scenario, i, planner_dir, folder, ranks)
        _wait(lambda f=folder: all(shard_done(f, k) for k in range(n_shards)), cfg.dagger.collect.wait_s, "shards")
        dirs = [str(run / "dagger" / f"iter-{j:03d}") for j in range(i + 1)]
        ckpt = run / "checkpoints" / f"iter-{i:03d}.ckpt"
        step = _train_iteration(cfg, i, source_planner, dirs, Path(prev["checkpoint"]) if prev else None, logger, ckpt)
        if ranks.is_main:
            planner = Planner.from_pretrained(ckpt, scenario)
            planner.extra.update(source="ttompc finetune", dagger_iteration=i, finetuned_from=str(source))
            out = planner.save(run / f"iter-{i:03d}" / "planner")
            metrics = _closed_loop(cfg, planner, eval_problems)
            _log(logger, metrics, i, step)
            state["completed"].append(
                {"iteration": i, "checkpoint": str(ckpt), "planner": str(out), "global_step": step, "metrics": metrics}
            )
            atomic_write_json(run / STATE_FILE, state)
        else:
            _wait(
                lambda k=i: len((_load_state(run) or {"completed": []})["completed"]) > k,
                cfg.dagger.collect.wait_s,
                f"rank 0 to finish iteration {i}",
            )
            state = _load_state(run) or state
    if logger is not None:
        logger.finalize("success")
        if type(logger).__name__ == "WandbLogger":  # close the run so a later fine-tuning can resume it
            logger.experiment.finish()
    return FinetuneResult(run, state["completed"], state["baseline_metrics"] or {})


def _log(logger: Any, metrics: dict[str, float], iteration: int, step: int) -> None:
    if logger is None:
        return
    logger.log_metrics({**{f"dagger/{k}": v for k, v in metrics.items()}, "dagger/iteration": iteration}, step=step)
    logger.save()
