"""The DAgger iteration loop (paper Alg. 1): collect, aggregate, train, measure, keep or reject; resumable, multi-rank.

Before it writes, measures or collects anything, ``check_inputs`` refuses a model, recipe and open-loop dataset that
do not belong together (scenario, normalisation statistics, labels), on a resumed run too.

Iteration i starts from its *parent*, the best model so far (the pretrained model, or the last kept iteration):

1. **Collect** ``dagger.collect.rollouts`` rollouts with the parent into ``<run>/dagger/iter-<i>/``
   (``ttompc.finetune.collect``).
2. **Train** ``dagger.steps_per_iteration`` optimiser steps from the parent's weights and optimiser state on the
   open-loop data mixed with every DAgger folder so far (``data.open_loop_fraction`` and ``data.closed_loop_share``;
   "grow" is the paper's mix) into ``<run>/checkpoints/iter-<i>.ckpt``.
3. **Measure** the candidate's closed-loop TTO-MPC as the measurement ``dagger.eval`` says (its fixed held-out
   problems, horizon and protocol; the metrics the training callback logs,
   ``ttompc.evaluation.episodes.closed_loop_metrics``)
   and **keep** it only if it ``improves`` on the parent; otherwise the next iteration starts again from the
   parent. A rejected iteration's rollouts stay in the aggregate: its visited states carry valid expert labels.

After the last iteration the selected model is exported to ``<run>/planner``. The fine-tuned model is therefore
never worse than its pretrained parent by that measure; it *is* the parent when no iteration improved.

``<run>/dagger_state.json`` records the source, the protocol of the measurement (``protocol_record``), the
pretrained model's metrics, the current best and, per iteration, its checkpoint, planner, global step, metrics,
parent, the keep/reject decision with its reason and the wall seconds of its phases (also logged as ``dagger/*``
metrics and printed); the exported planner keeps the protocol record (``dagger_protocol``). Re-running the same
command continues: finished iterations are skipped, done rollout shards are not recollected, and an iteration whose
training was interrupted resumes from its checkpoint (refreshed every ``trainer.checkpoint_every_n_steps`` and on
an exception such as Ctrl-C).
Ranks: every rank collects its own shards and trains (Lightning strategy); rank 0 measures and decides, and the other
ranks wait for its decision in the state file.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ttompc.config import to_container
from ttompc.data.distributed import RankInfo, rank_info
from ttompc.data.shards import atomic_write_json
from ttompc.errors import UserError
from ttompc.finetune.collect import collect_iteration, rollout_folder
from ttompc.finetune.config import FinetuneConfig
from ttompc.outputs import claim_folder
from ttompc.progress import status
from ttompc.ranges import check_devices

if TYPE_CHECKING:
    from ttompc.evaluation.problems import EvalProblem
    from ttompc.policy import Planner
    from ttompc.scenarios.base import Scenario

STATE_FILE = "dagger_state.json"
SOURCE_PLANNER = "source-planner"
PLANNER = "planner"  # the exported, selected model
INHERITED_EXTRA = ("rtg_scale",)  # bundle metadata a fine-tuned model keeps from its source


class FinetuneError(UserError, ValueError):
    """A run folder or dataset that does not match the requested fine-tuning (the CLI prints it as one line)."""


@dataclass
class FinetuneResult:
    run_dir: Path
    iterations: list[dict[str, Any]]  # one record per finished iteration (see the module docstring)
    baseline_metrics: dict[str, float | None]  # the pretrained model's closed-loop metrics (None: not finite)
    best_iteration: int  # the exported model's iteration; -1: the pretrained model (no iteration improved)
    planner_dir: Path | None  # the exported model (rank 0)


def improves(candidate: dict[str, float | None], best: dict[str, float | None]) -> tuple[bool, str]:
    """Whether closed-loop ``candidate`` metrics beat ``best``, and why: fewer infeasible episodes, or as many and a
    lower mean relative cost increment (J − J_REL)/J_REL over the feasible ones (None or nan: no feasible episode).
    Ties are not improvements."""
    ci, bi = candidate["infeasible"], best["infeasible"]
    if ci != bi:
        return ci < bi, f"infeasible episodes {ci:g} vs {bi:g}"  # type: ignore[operator]
    cc, bc = _number(candidate["cost_increment"]), _number(best["cost_increment"])
    if math.isnan(cc) or math.isnan(bc):
        return False, f"no feasible episode to compare (infeasible {ci:g})"
    return cc < bc, f"cost increment {cc:.4g} vs {bc:.4g} (infeasible {ci:g})"


def _number(x: float | None) -> float:
    return float("nan") if x is None else float(x)


def _json_safe(metrics: dict[str, float]) -> dict[str, float | None]:
    """Metrics for the state file: nan (e.g. a standard error of one episode) as null, which JSON can hold."""
    return {k: (v if math.isfinite(v) else None) for k, v in metrics.items()}


def _load_state(run: Path) -> dict[str, Any] | None:
    import json

    path = run / STATE_FILE
    if not path.is_file():
        return None
    state = json.loads(path.read_text())
    if "best" not in state:
        raise FinetuneError(f"{path} was written by an older ttompc (no keep/reject record)", "use another out_dir")
    return state


def _finished(run: Path) -> int:
    """Iterations rank 0 has recorded (other ranks poll this)."""
    state = _load_state(run)
    return len(state["completed"]) if state else 0


def _wait(predicate: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"gave up waiting {timeout:.0f} s for {what}")
        time.sleep(2.0)


def protocol_record(cfg: FinetuneConfig, scenario: Scenario) -> dict[str, Any]:
    """What the state file and the exported bundle record of the measurement's settings: the protocol, its
    overrides, the resolved settings and the solver path (chain and trust-region norm)."""
    from dataclasses import asdict

    from ttompc.solvers.backends import solver_path

    m = cfg.dagger.eval
    return {
        "name": m.protocol,
        "overrides": dict(m.mpc),
        "settings": asdict(m.settings),
        "solver": solver_path(m.settings.backend, scenario),
        "robust_blend": m.robust_blend,
    }


def measure(cfg: FinetuneConfig, planner: Planner, problems: list[EvalProblem]) -> dict[str, float]:
    """Closed-loop TTO-MPC metrics of ``planner`` on the problems of the measurement ``dagger.eval`` (one torch
    thread: batch-1 rollouts)."""
    from ttompc.evaluation.episodes import closed_loop_metrics
    from ttompc.parallel import single_torch_thread

    with single_torch_thread():
        metrics, _ = closed_loop_metrics(planner, cfg.dagger.eval, problems, progress="measure")
    return metrics


def check_value_labels(cfg: FinetuneConfig, planner: Planner) -> None:
    """A model with a value output learns it from DAgger rows too, whose rtg must then be a cost-to-go from the
    labelled steps on: plan labels with the expert's rtg (``labels.kind=plan``, ``labels.rtg=expert``); raises
    ``FinetuneError`` otherwise."""
    labels = cfg.dagger.labels
    if planner.has_value and (labels.kind, labels.rtg) != ("plan", "expert"):
        raise FinetuneError(
            f"the model has a value output, which learns the rtg of DAgger rows as a cost-to-go, but "
            f"dagger.labels.kind={labels.kind} dagger.labels.rtg={labels.rtg} rows carry the learner's running value",
            "use dagger.labels.kind=plan dagger.labels.rtg=expert",
        )


def claim_run(cfg: FinetuneConfig) -> None:
    """The devices ``cfg`` names exist here, and ``trainer.out_dir`` is new, empty or a DAgger run's (its state file
    or source planner: ``finetune`` checks its source and seed itself); ``ConfigError``/``UserError`` otherwise, in
    the words of ``ttompc finetune``."""
    check_devices(cfg)
    claim_folder(cfg.trainer.out_dir, "finetune", lambda f: (f / STATE_FILE).is_file() or (f / SOURCE_PLANNER).is_dir())


def _model_name(iteration: int) -> str:
    """How messages name a DAgger model: iteration -1 of the state file is the pretrained model."""
    return "the pretrained model" if iteration < 0 else f"iteration {iteration}"


def check_inputs(cfg: FinetuneConfig, planner: Planner, source: str) -> None:
    """Whether ``cfg`` can fine-tune ``planner`` (loaded from ``source``), decided from the recipe, the model and the
    datasets' manifests alone (no shard is read), so that a mismatch costs seconds, not a measurement and a
    collection: the recipe's scenario (``data.scenario``, when set) is the model's; every ``data.paths`` folder
    exists, is a finished dataset that fits the recipe (``ttompc.data.manifests.check_datasets``) and holds the
    model's scenario with its normalisation statistics (the data it was trained on); the labels suit its outputs
    (``check_value_labels``). Raises a ``UserError`` (one line naming the mismatch and what to do)."""
    from ttompc.data.manifests import check_datasets
    from ttompc.policy.stats import NormStats

    model = planner.scenario.name
    if cfg.data.scenario is not None and cfg.data.scenario != model:
        raise FinetuneError(
            f"the model {source} is a {model} model but the recipe is for {cfg.data.scenario} (data.scenario)",
            f"fine-tune it with a recipe of recipes/{model}/, or pick a {cfg.data.scenario} model (`ttompc zoo list`)",
        )
    missing = [p for p in cfg.data.paths if not Path(p).is_dir()]
    if missing:  # generating a new dataset would not do: its normalisation statistics would not be the model's
        recorded = (planner.recipe.get("data") or {}).get("paths") or []
        trained_on = f" (recorded in the model: {', '.join(map(str, recorded))})" if recorded else ""
        what = "is a file, not a dataset folder" if Path(missing[0]).exists() else "does not exist"
        raise FinetuneError(
            f"data.paths: dataset folder {missing[0]} {what}",
            f"fine-tuning needs the open-loop dataset the model was trained on{trained_on}: point data.paths=[...] "
            "at it, or remake it with the `ttompc generate` command of the model's recipe or data card (the same "
            "settings make the same data)",
        )
    first = check_datasets(cfg.data)[0]
    path, data = cfg.data.paths[0], first["scenario"]["name"]
    if data != model:
        raise FinetuneError(
            f"data.paths: {path} holds {data} trajectories but the model {source} is a {model} model",
            "point data.paths at the open-loop dataset the model was trained on",
        )
    stats = NormStats.from_dict(first["norm_stats"])
    # the same data, regenerated by the same command with a later solver, differs by its optima's rounding: the
    # free-flyer's data/freeflyer-v3 0.12% in the states' spread, 2e-5 in their mean; another dataset by far more
    for key in ("states", "actions", "rtg", "ctg"):
        if not np.allclose(stats.mean[key], planner.stats.mean[key], rtol=1e-2, atol=1e-3) or not np.allclose(
            stats.std[key], planner.stats.std[key], rtol=1e-2, atol=1e-3
        ):
            raise FinetuneError(
                f"data.paths: the normalisation statistics of {path} ({key}) differ from those of the model {source}",
                "fine-tune on the open-loop dataset the model was trained on",
            )
    check_value_labels(cfg, planner)


def _train_iteration(
    cfg: FinetuneConfig,
    iteration: int,
    source: Planner,
    parent: dict[str, Any],
    dagger_dirs: list[str],
    logger: Any,
    ckpt: Path,
) -> int:
    """Train ``steps_per_iteration`` steps from ``parent`` into ``ckpt`` (or continue an interrupted run of this
    iteration from ``ckpt``); returns the global step reached."""
    import lightning as L

    from ttompc.data.datamodule import TrajectoryDataModule
    from ttompc.training.checkpoints import ExceptionCheckpoint, checkpoint_step
    from ttompc.training.module import SaveLastCheckpoint, build_module
    from ttompc.training.run import build_trainer, fit

    target = int(parent["global_step"]) + cfg.dagger.steps_per_iteration
    resume_from: Path | None = None
    if ckpt.is_file():
        if checkpoint_step(ckpt) >= target:
            return checkpoint_step(ckpt)  # trained before the state file recorded it
        resume_from = ckpt
    elif parent["checkpoint"] is not None:
        resume_from = Path(parent["checkpoint"])
    L.seed_everything(cfg.trainer.seed + iteration, workers=True, verbose=False)
    dm = TrajectoryDataModule(replace(cfg.data, dagger_dirs=dagger_dirs, seed=cfg.data.seed + iteration))
    dm.setup("fit")
    module = build_module(
        source.model.cfg,
        cfg.optim,
        source.scenario,
        source.stats,
        recipe=cfg,
        plot_trajectories=False,
        backend=cfg.dagger.eval.settings.backend,
    )
    if resume_from is None:
        module.model.load_state_dict(source.model.state_dict())
    t = cfg.trainer
    callbacks: list[L.Callback] = [SaveLastCheckpoint(ckpt, t.checkpoint_every_n_steps), ExceptionCheckpoint(ckpt)]
    if cfg.callbacks.eval_mpc.enabled:  # the model's closed loop while it fine-tunes (logged as mpc/*)
        from ttompc.training.callbacks import ClosedLoopEvalCallback

        callbacks.append(ClosedLoopEvalCallback.from_config(cfg.callbacks.eval_mpc, source.scenario.name))
    trainer = build_trainer(
        replace(t, max_steps=target),
        cfg.optim,
        Path(t.out_dir),
        logger,
        callbacks=callbacks,
        enable_checkpointing=False,
    )
    fit(trainer, module, dm, resume_from)
    return checkpoint_step(ckpt)


def _log(logger: Any, metrics: dict[str, float], iteration: int, step: int) -> None:
    if logger is None:
        return
    logger.log_metrics({**{f"dagger/{k}": v for k, v in metrics.items()}, "dagger/iteration": iteration}, step=step)
    logger.save()


def _export(run: Path, state: dict[str, Any], source: str) -> Path:
    """Write the selected model to ``<run>/planner`` (the pretrained one when no iteration was kept)."""
    from ttompc.policy import Planner

    best = state["best"]
    planner = Planner.from_pretrained(best["planner"])
    planner.extra.update(
        source="ttompc finetune",
        finetuned_from=source,
        dagger_iteration=best["iteration"],
        dagger_kept=[r["iteration"] for r in state["completed"] if r["kept"]],
        dagger_metrics=best["metrics"],
        dagger_baseline_metrics=state["baseline_metrics"],
        dagger_protocol=state.get("protocol"),  # the settings its metrics were measured under
    )
    return planner.save(run / PLANNER)


def finetune(cfg: FinetuneConfig, source: str, ranks: RankInfo | None = None) -> FinetuneResult:
    """Run (or resume) DAgger fine-tuning of ``source`` (zoo name, bundle folder or checkpoint) in
    ``cfg.trainer.out_dir``; see the module docstring."""
    from ttompc.policy import Planner
    from ttompc.training.loggers import build_logger, finish_logger

    ranks = ranks or rank_info()
    run = Path(cfg.trainer.out_dir)
    claim_run(cfg)
    state = _load_state(run)
    if state is not None and state["source"] != str(source):
        raise FinetuneError(f"{run} fine-tunes {state['source']!r}, not {source!r}", "use another trainer.out_dir")
    if state is not None and state["seed"] != cfg.dagger.seed:  # its rollouts so far were drawn with that seed
        raise FinetuneError(f"{run} was collected with dagger.seed={state['seed']}", "keep it or use another out_dir")
    src_dir = run / SOURCE_PLANNER
    if ranks.is_main:  # checked before anything is written, measured or collected (a resumed run's data too)
        saved = (src_dir / "config.json").is_file()
        pretrained = Planner.from_pretrained(src_dir if saved else source)
        check_inputs(cfg, pretrained, str(source))
        run.mkdir(parents=True, exist_ok=True)
        if not saved:
            pretrained.save(src_dir)
    wait_s = cfg.dagger.collect.wait_s
    _wait(lambda: (src_dir / "config.json").is_file(), wait_s, "the source planner")
    source_planner = Planner.from_pretrained(src_dir)
    scenario = source_planner.scenario
    logger = build_logger(cfg.logger, run, to_container(cfg)) if ranks.is_main else None
    problems = cfg.dagger.eval.problem_set(scenario, progress="held-out problems (REL)") if ranks.is_main else []
    if state is None and ranks.is_main:
        n = len(problems)
        status(f"ttompc finetune: measuring the pretrained model (closed-loop TTO-MPC, {n} problem{'s' * (n != 1)})")
        measured = measure(cfg, source_planner, problems)
        _log(logger, measured, -1, 0)
        baseline = _json_safe(measured)
        best = {"iteration": -1, "planner": str(src_dir), "checkpoint": None, "global_step": 0, "metrics": baseline}
        state = {
            "source": str(source),
            "seed": cfg.dagger.seed,
            "protocol": protocol_record(cfg, scenario),
            "baseline_metrics": baseline,
            "best": best,
            "completed": [],
        }
        atomic_write_json(run / STATE_FILE, state)
    elif state is None:
        _wait(lambda: (run / STATE_FILE).is_file(), wait_s, "rank 0 to measure the pretrained model")
        state = _load_state(run)
    assert state is not None
    c = cfg.dagger.collect
    for i in range(len(state["completed"]), cfg.dagger.iterations):
        parent = state["best"]
        status(
            f"ttompc finetune: iteration {i} ({i + 1} of {cfg.dagger.iterations}): {c.rollouts} rollouts with "
            f"{_model_name(parent['iteration'])}, then {cfg.dagger.steps_per_iteration} training steps"
        )
        folder = rollout_folder(run / "dagger" / f"iter-{i:03d}", scenario, c.rollouts, c.shard_size)
        t0 = time.perf_counter()
        collect_iteration(cfg.dagger, scenario, i, Path(parent["planner"]), folder, ranks)
        t1 = time.perf_counter()
        if not folder.wait(wait_s):
            raise TimeoutError(f"gave up waiting {wait_s:.0f} s for other ranks' rollout shards in {folder.root}")
        dirs = [str(run / "dagger" / f"iter-{j:03d}") for j in range(i + 1)]
        ckpt = run / "checkpoints" / f"iter-{i:03d}.ckpt"
        step = _train_iteration(cfg, i, source_planner, parent, dirs, logger, ckpt)
        t2 = time.perf_counter()
        if ranks.is_main:
            candidate = Planner.from_pretrained(ckpt, scenario)
            # the candidate plans with its source's conditioning (rtg_0 = -rtg_scale * J_REL, chosen for the
            # source and recorded in its bundle): measured against the source at the same rtg_scale, and exported
            # with it (docs/design.md, "Measurements behind the code")
            inherited = {k: source_planner.extra[k] for k in INHERITED_EXTRA if k in source_planner.extra}
            candidate.extra.update(
                source="ttompc finetune", dagger_iteration=i, finetuned_from=str(source), **inherited
            )
            out = candidate.save(run / f"iter-{i:03d}" / "planner")
            status(f"ttompc finetune: measuring iteration {i} against {_model_name(parent['iteration'])}")
            measured = measure(cfg, candidate, problems)
            metrics = _json_safe(measured)
            kept, reason = improves(metrics, parent["metrics"])
            # wall seconds of this process's phases (a resumed phase counts from the resume)
            seconds = {"collect": t1 - t0, "train": t2 - t1, "measure": time.perf_counter() - t2}
            record = {
                "iteration": i,
                "checkpoint": str(ckpt),
                "planner": str(out),
                "global_step": step,
                "metrics": metrics,
                "parent": parent["iteration"],
                "kept": kept,
                "reason": reason,
                "seconds": seconds,
            }
            state["completed"].append(record)
            if kept:
                state["best"] = {k: record[k] for k in ("iteration", "planner", "checkpoint", "global_step", "metrics")}
            _log(
                logger, {**measured, "kept": float(kept), "best_iteration": float(state["best"]["iteration"])}, i, step
            )
            print(
                f"ttompc finetune: iteration {i} {'kept' if kept else 'rejected'} against "
                f"{_model_name(parent['iteration'])} ({reason})",
                file=sys.stderr,
            )
            atomic_write_json(run / STATE_FILE, state)
        else:
            _wait(lambda: _finished(run) > i, wait_s, f"rank 0 to finish iteration {i}")  # noqa: B023
            state = _load_state(run) or state
    planner_dir = _export(run, state, str(source)) if ranks.is_main else None
    if logger is not None:
        logger.finalize("success")
        finish_logger(logger)  # close the run so a later fine-tuning in this process starts or resumes its own
    return FinetuneResult(run, state["completed"], state["baseline_metrics"], state["best"]["iteration"], planner_dir)
