"""Closed-loop metrics of MPC episodes (used by ``ttompc evaluate mpc``, the training callback and DAgger).

Costs are only averaged over episodes that are *feasible* (all N steps run, no keep-out violation, path constraints
met, goal reached within ``terminal_tol``): an infeasible, goal-missing or truncated run has no meaningful cost, so
it is counted apart (``infeasible``; of those, ``truncated``: cut at ``max_steps``) and never averaged into one.
Every mean comes with its standard error and a seeded percentile bootstrap interval
(``ttompc.evaluation.stats.interval``), so two models can be told apart from noise.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from ttompc.evaluation.measurement import Measurement
from ttompc.evaluation.problems import EvalProblem
from ttompc.evaluation.stats import interval
from ttompc.mpc.episode import Episode, rel_increment
from ttompc.mpc.loop import run_mpc_batch
from ttompc.mpc.methods import MethodInputs, model_method

if TYPE_CHECKING:
    from ttompc.policy import Planner


def episode_record(e: Episode) -> dict[str, Any]:
    """An episode's summary plus the relative cost increment (J − J_REL)/J_REL (``rel_increment``: nan when
    infeasible or without J_REL)."""
    r = e.summary()
    r["rel_increment"] = rel_increment(e.cost, e.rel_cost, e.feasible)
    return r


def summarize_episodes(records: Sequence[dict[str, Any]], *, seed: int = 0) -> dict[str, Any]:
    """Counts (runs, feasible, infeasible, truncated: cut at ``max_steps``, counted as infeasible), intervals of the
    relative cost increment and applied cost over the feasible runs, plan consistency, step times, SCP iterations
    (the mean over runs of each run's ``mean_iterations`` and ``mean_iterations_solved``, ``Episode.summary``),
    fallbacks and the goal miss of the infeasible runs of a group of episode records."""
    feasible = [r for r in records if r["feasible"]]
    return {
        "runs": len(records),
        "feasible": len(feasible),
        "infeasible": len(records) - len(feasible),
        "truncated": sum(not r["complete"] for r in records),
        "rel_increment": interval([r["rel_increment"] for r in feasible], seed=seed),
        "cost": interval([r["cost"] for r in feasible], seed=seed),
        "target_change": interval([r["target_change"] for r in records], seed=seed),
        "mean_step_time": float(np.mean([r["mean_step_time"] for r in records])) if records else float("nan"),
        "max_step_time": float(np.max([r["max_step_time"] for r in records])) if records else float("nan"),
        "mean_iterations": float(np.mean([r["mean_iterations"] for r in records])) if records else float("nan"),
        "mean_iterations_solved": (
            float(np.mean([r["mean_iterations_solved"] for r in records])) if records else float("nan")
        ),
        "fallbacks": int(sum(r["fallbacks"] for r in records)),
        "infeasible_terminal_error": interval(
            [r["terminal_error"] for r in records if not r["feasible"]], seed=seed
        ),  # how far the infeasible runs ended from the goal
    }


def closed_loop_metrics(
    planner: Planner,
    measurement: Measurement,
    problems: Sequence[EvalProblem],
    *,
    progress: str = "",
) -> tuple[dict[str, float], list[Episode]]:
    """TTO-MPC, or R-TTO-MPC when ``measurement.robust_blend`` > 0 (``METHODS``), with ``planner`` (conditioned at
    its own ``rtg_scale``) on fixed ``problems``
    (``measurement.problem_set``) as the single-horizon, single-plant ``measurement`` says (its settings, horizon,
    plant and max_steps; the perturbed plant seeded per problem), all episodes in lockstep with one batched rollout
    per step: flat metrics for loggers — ``feasible_rate``, ``infeasible`` (count; ``truncated``: of those, the
    episodes cut at ``max_steps``, which never reach the goal),
    ``cost_increment`` and its ``_se`` (mean (J − J_REL)/J_REL over feasible runs, nan if none), ``cost`` (feasible
    runs), ``target_change``, step times (``Episode.step_times``: each episode's share of the batched rollout and
    context advance plus its own solves) and ``fallbacks``. ``progress``: the label of a progress bar over the
    episodes on stderr ("": none)."""
    from ttompc.progress import Bar

    sc = planner.scenario
    measurement.check_single("closed_loop_metrics")
    [(_, run)] = measurement.runs(sc)
    blend = measurement.robust_blend
    provs = model_method("TTO", blend > 0).providers(MethodInputs(run.settings, [None] * len(problems), planner, blend))
    steps = min(run.max_steps or sc.n_steps, sc.n_steps)
    with Bar(len(problems), progress, "episode", show=bool(progress)) as bar:
        episodes = run_mpc_batch(
            sc, [ep.start for ep in problems], provs, run, on_step=lambda: bar.update(len(provs) / steps)
        )
    summary = summarize_episodes([episode_record(e) for e in episodes])
    times = np.concatenate([e.step_times for e in episodes])
    metrics = {
        "feasible_rate": summary["feasible"] / max(summary["runs"], 1),
        "infeasible": float(summary["infeasible"]),
        "truncated": float(summary["truncated"]),
        "cost_increment": summary["rel_increment"]["mean"],
        "cost_increment_se": summary["rel_increment"]["se"],
        "cost": summary["cost"]["mean"],
        "target_change": summary["target_change"]["mean"],
        "step_time_mean": float(np.mean(times)),
        "step_time_max": float(np.max(times)),
        "fallbacks": float(summary["fallbacks"]),
    }
    return metrics, episodes
