"""Bootstrap statistics of the evaluation reports: means with their standard error and a seeded percentile
bootstrap interval, so two models can be told apart from noise (``interval``), and their table format."""

from __future__ import annotations

import math
from collections.abc import Sequence

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
