"""Closed-loop metrics of MPC episodes, next to the loop that produces them (used by ``ttompc evaluate mpc``, the
training callback and DAgger).

Costs are only averaged over episodes that are *feasible* (no keep-out violation, path constraints met, goal
reached within ``terminal_tol``): an infeasible or goal-missing run has no meaningful cost, so it is counted apart
(``infeasible``) and never averaged into one. Every mean comes with its standard error and a seeded percentile
bootstrap interval (``interval``), so two models can be told apart from noise.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from ttompc.mpc.loop import Episode, run_mpc_batch
from ttompc.mpc.plant import PlantNoise
from ttompc.mpc.providers import RolloutGroup, TerminalDesign, TTOProvider
from ttompc.mpc.settings import MPCSettings
from ttompc.scenarios.base import Problem

if TYPE_CHECKING:
    from ttompc.policy import Planner

BOOTSTRAP_SAMPLES = 2000


def interval(values: Sequence[float] | np.ndarray, *, level: float = 0.95, seed: int = 0) -> dict[str, float]:
    """Mean of the finite ``values`` with its standard error and a percentile bootstrap interval at ``level``
    (``BOOTSTRAP_SAMPLES`` resamples from ``default_rng(seed)``): keys mean, se, lo, hi and n (the number of finite
    values). With no value everything is nan; with one, the s.e. and interval are nan."""
    x = np.asarray([v for v in values if v is not None and math.isfinite(v)], dtype=np.float64)
    out = {"mean": float("nan"), "se": float("nan"), "lo": float("nan"), "hi": float("nan"), "n": len(x)}
    if len(x) == 0:
        return out
    out["mean"] = float(np.mean(x))
    if len(x) < 2:
        return out
    out["se"] = float(np.std(x, ddof=1) / np.sqrt(len(x)))
    idx = np.random.default_rng(seed).integers(0, len(x), size=(BOOTSTRAP_SAMPLES, len(x)))
    out["lo"], out["hi"] = (float(v) for v in np.quantile(x[idx].mean(axis=1), [(1 - level) / 2, (1 + level) / 2]))
    return out


def format_interval(iv: dict[str, float], scale: float = 1.0, digits: int = 3) -> str:
    """'mean ± se [lo, hi]' (times ``scale``) for tables."""
    if not iv["n"]:
        return "–"
    m, se, lo, hi = (iv[k] * scale for k in ("mean", "se", "lo", "hi"))
    if not math.isfinite(se):
        return f"{m:.{digits}g}"
    return f"{m:.{digits}g} ± {se:.2g} [{lo:.{digits}g}, {hi:.{digits}g}]"


def episode_record(e: Episode) -> dict[str, Any]:
    """An episode's summary plus the relative cost increment (J − J_REL)/J_REL (nan when infeasible)."""
    r = e.summary()
    r["rel_increment"] = float((e.cost - e.rel_cost) / abs(e.rel_cost)) if e.feasible else float("nan")
    return r


def summarize_episodes(records: Sequence[dict[str, Any]], *, seed: int = 0) -> dict[str, Any]:
    """Counts (runs, feasible, infeasible), intervals of the relative cost increment and applied cost over the
    feasible runs, plan consistency, step times, fallbacks and the goal miss of the infeasible runs of a group of
    episode records."""
    feasible = [r for r in records if r["feasible"]]
    return {
        "runs": len(records),
        "feasible": len(feasible),
        "infeasible": len(records) - len(feasible),
        "rel_increment": interval([r["rel_increment"] for r in feasible], seed=seed),
        "cost": interval([r["cost"] for r in feasible], seed=seed),
        "target_change": interval([r["target_change"] for r in records], seed=seed),
        "mean_step_time": float(np.mean([r["mean_step_time"] for r in records])) if records else float("nan"),
        "max_step_time": float(np.max([r["max_step_time"] for r in records])) if records else float("nan"),
        "fallbacks": int(sum(r["fallbacks"] for r in records)),
        "infeasible_terminal_error": interval(
            [r["terminal_error"] for r in records if not r["feasible"]], seed=seed
        ),  # how far the infeasible runs ended from the goal
    }


class ProblemWithRel(Protocol):
    """What closed-loop metrics need of an evaluation problem (``ttompc.evaluation.problems.EvalProblem``)."""

    seed: int
    problem: Problem

    @property
    def rel_cost(self) -> float: ...


def closed_loop_metrics(
    planner: Planner,
    problems: Sequence[ProblemWithRel],
    horizon: int,
    *,
    settings: MPCSettings | None = None,
    name: str = "TTO-MPC",
    max_steps: int | None = None,
    plant: PlantNoise | None = None,
    rtg_scale: float | None = None,
    progress: str = "",
) -> tuple[dict[str, float], list[Episode]]:
    """TTO-MPC with ``planner`` and ``settings`` (default: the paper's) on fixed problems (optionally on the
    perturbed ``plant``, seeded per problem), all episodes in lockstep with one batched rollout per step
    (``RolloutGroup``): flat metrics for loggers — ``feasible_rate``, ``infeasible`` (count), ``cost_increment`` and
    its ``_se`` (mean (J − J_REL)/J_REL over feasible runs, nan if none), ``cost`` (feasible runs),
    ``target_change``, step times (each episode's share of the batched rollout plus its own solves) and
    ``fallbacks``. ``progress``: the label of a progress bar over the episodes on stderr ("": none)."""
    from ttompc.progress import Bar

    sc = planner.scenario
    s = settings or MPCSettings()
    group = RolloutGroup(planner)
    design = TerminalDesign(weights=None if s.track is None else (s.track,))
    provs = [
        TTOProvider(planner, name, rtg_scale=rtg_scale, design=design, rtg_mode=s.rtg_mode, group=group,
                    backend=s.backend)
        for _ in problems
    ]  # fmt: skip
    steps = min(max_steps or sc.n_steps, sc.n_steps)
    with Bar(len(problems), progress, "episode", show=bool(progress)) as bar:
        episodes = run_mpc_batch(sc, [ep.problem for ep in problems], provs, horizon,
                                 rel_costs=[ep.rel_cost for ep in problems], settings=s, max_steps=max_steps,
                                 plant=plant, plant_seeds=[ep.seed for ep in problems],
                                 on_step=lambda: bar.update(len(provs) / steps))  # fmt: skip
    summary = summarize_episodes([episode_record(e) for e in episodes])
    times = np.concatenate([e.step_times for e in episodes])
    metrics = {
        "feasible_rate": summary["feasible"] / max(summary["runs"], 1),
        "infeasible": float(summary["infeasible"]),
        "cost_increment": summary["rel_increment"]["mean"],
        "cost_increment_se": summary["rel_increment"]["se"],
        "cost": summary["cost"]["mean"],
        "target_change": summary["target_change"]["mean"],
        "step_time_mean": float(np.mean(times)),
        "step_time_max": float(np.max(times)),
        "fallbacks": float(summary["fallbacks"]),
    }
    return metrics, episodes
