"""Bootstrap statistics of the evaluation reports: means with their standard error and a seeded percentile
bootstrap interval, so two models can be told apart from noise (``interval``), and their table format; and the one
paired comparison of two methods on the problems both ran (``paired``), which ``ttompc evaluate compare``, the
closed-loop report and the demo read; and its per-problem form for curves of fixed problems (``paired_points``)."""

from __future__ import annotations

import math
from collections.abc import Hashable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

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


@dataclass(frozen=True)
class Outcome:
    """What a paired comparison reads of one episode: whether it ran feasibly (goal reached, every constraint met),
    its (J − J_REL)/J_REL (nan when infeasible) and its mean step time (s)."""

    feasible: bool
    rel_increment: float
    step_time: float

    @classmethod
    def of(cls, record: Mapping[str, Any]) -> Outcome:
        """From an episode record (``ttompc.evaluation.episodes.episode_record``, a report's run)."""
        return cls(bool(record["feasible"]), float(record["rel_increment"]), float(record["mean_step_time"]))


def paired(
    base: Mapping[Hashable, Outcome], other: Mapping[Hashable, Outcome], *, scale: float = 1.0, seed: int = 0
) -> dict[str, Any]:
    """Method ``other`` against ``base`` on the problems both ran (keys, in ``other``'s order): ``problems`` (how
    many), ``base_goals`` / ``other_goals`` (feasible episodes among them), ``lost`` (feasible in the base only),
    ``won`` (in the other only), ``paired``: the ``interval`` (mean, standard error, 95% bootstrap lo/hi, n) of
    ``scale``·(other − base) in (J − J_REL)/J_REL over the n problems both ran feasibly (negative: the other is
    cheaper), ``base_step_time`` / ``other_step_time``: the mean step times over the problems both ran (feasible or
    not) and ``step_ratio``: base / other (> 1: the other steps faster). ``seed`` seeds the bootstrap."""
    problems = [p for p in other if p in base]
    b, o = [base[p] for p in problems], [other[p] for p in problems]
    both = [(x, y) for x, y in zip(b, o, strict=True) if x.feasible and y.feasible]
    base_step, other_step = _finite_mean(x.step_time for x in b), _finite_mean(y.step_time for y in o)
    return {
        "problems": len(problems),
        "base_goals": sum(x.feasible for x in b),
        "other_goals": sum(y.feasible for y in o),
        "lost": sum(x.feasible and not y.feasible for x, y in zip(b, o, strict=True)),
        "won": sum(y.feasible and not x.feasible for x, y in zip(b, o, strict=True)),
        "paired": interval([scale * (y.rel_increment - x.rel_increment) for x, y in both], seed=seed),
        "base_step_time": base_step,
        "other_step_time": other_step,
        "step_ratio": base_step / other_step if other_step > 0 else float("nan"),
    }


def _finite_mean(values: Iterable[float]) -> float:
    x = [v for v in values if math.isfinite(v)]
    return float(np.mean(x)) if x else float("nan")


def paired_points(model: Sequence[float | None], base: Sequence[float | None]) -> dict[str, float]:
    """``model − base`` per problem (two lists of one value per problem, None or nan where that side missed the
    goal) over the problems both finished: mean, standard error and ``n`` (``interval``'s), in the units given (e.g.
    fractions of J_REL), with ``goals`` / ``baseline_goals``: the problems each side finished. Lists of different
    lengths raise ``ValueError``."""
    a = np.array([np.nan if v is None else v for v in model], float)
    b = np.array([np.nan if v is None else v for v in base], float)
    if a.shape != b.shape:
        raise ValueError(f"paired increments need one value per problem on both sides, got {a.shape} vs {b.shape}")
    both = ~np.isnan(a) & ~np.isnan(b)
    iv = interval(a[both] - b[both])
    return {
        "mean": iv["mean"],
        "se": iv["se"],
        "n": int(iv["n"]),
        "goals": int((~np.isnan(a)).sum()),
        "baseline_goals": int((~np.isnan(b)).sum()),
    }
