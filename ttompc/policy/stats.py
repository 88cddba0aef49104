"""Normalisation statistics of a trajectory dataset: global per-dimension mean/std over all samples and steps (the
authors' research code's ``timestep_norm=False``), for the five modalities. Stored in dataset manifests and
checkpoints as plain lists, so a checkpoint alone is enough to plan.

They belong to the policy (a planner cannot normalise without them); the data package computes them and imports
this module, which needs only NumPy, so data depends on the policy for statistics and never the reverse."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

KEYS = ("states", "actions", "goals", "rtg", "ctg")
EPS = 1e-6  # added to σ like the reference, so constant dimensions (RPOD goal) normalise to 0


@dataclass
class NormStats:
    """Per-modality mean and std (float64 arrays, one value per feature). Treat as read-only once used: tensor copies
    are cached per dtype and device."""

    mean: dict[str, np.ndarray]
    std: dict[str, np.ndarray]
    # (key, dtype, device) -> (μ, σ + ε) as tensors: the rollout normalises every step, converting once is cheaper
    _tensors: dict[tuple[str, Any, Any], tuple[Any, Any]] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        missing = [k for k in KEYS if k not in self.mean or k not in self.std]
        if missing:
            raise ValueError(f"NormStats is missing entries for {missing}")
        self.mean = {k: np.asarray(v, dtype=np.float64).reshape(-1) for k, v in self.mean.items()}
        self.std = {k: np.asarray(v, dtype=np.float64).reshape(-1) for k, v in self.std.items()}

    def normalize(self, key: str, x: Any) -> Any:
        """(x − μ)/(σ + ε) for numpy arrays or torch tensors (last axis = feature dim), in x's dtype."""
        mu, sd = self.mean_std(key, x)
        return (x - mu) / sd

    def denormalize(self, key: str, x: Any) -> Any:
        mu, sd = self.mean_std(key, x)
        return x * sd + mu

    def mean_std(self, key: str, x: Any) -> tuple[Any, Any]:
        """(μ, σ + ε) of ``key`` like ``x``: numpy arrays in x's dtype, torch tensors in x's dtype and device (cached:
        do not modify them)."""
        if isinstance(x, np.ndarray):
            return self.mean[key].astype(x.dtype, copy=False), self.std[key].astype(x.dtype, copy=False) + EPS
        slot = (key, x.dtype, x.device)
        if slot not in self._tensors:
            import torch

            as_t = lambda v: torch.as_tensor(v, dtype=x.dtype, device=x.device)  # noqa: E731
            self._tensors[slot] = (as_t(self.mean[key]), as_t(self.std[key]) + EPS)
        return self._tensors[slot]

    def to_dict(self) -> dict[str, dict[str, list[float]]]:
        return {
            "mean": {k: self.mean[k].tolist() for k in KEYS},
            "std": {k: self.std[k].tolist() for k in KEYS},
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> NormStats:
        try:
            return cls(mean=dict(d["mean"]), std=dict(d["std"]))
        except KeyError as err:
            raise ValueError(f"normalisation statistics need 'mean' and 'std', missing {err}") from None

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> NormStats:
        """Statistics over arrays shaped (..., dim) per key (all leading axes pooled)."""
        mean, std = {}, {}
        for k in KEYS:
            a = np.asarray(arrays[k], dtype=np.float64)
            a = a.reshape(-1, a.shape[-1]) if a.ndim > 1 else a.reshape(-1, 1)
            mean[k], std[k] = a.mean(axis=0), a.std(axis=0)
        return cls(mean, std)
