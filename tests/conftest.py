"""Shared fixtures. ``ToyScenario`` is a tiny obstacle-free double integrator (registered as "toy") so model,
rollout, planner and training tests do not depend on the real scenarios being finished or fast."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import helpers
import numpy as np
import pytest

from ttompc.policy.stats import NormStats
from ttompc.scenarios import register
from ttompc.scenarios.base import MPCWeights, Problem, Scenario, SCPSettings, Window

TOY_DT = 0.5
TOY_STEPS = 12


class _ToyTorch:
    """x_{k+1} = A x_k + B u_k on (pos3, vel3); 'violation' = being inside the unit ball (for ctg tests)."""

    def __init__(self, device: Any) -> None:
        import torch

        self._A = torch.as_tensor(_toy_A(), device=device)
        self._B = torch.as_tensor(_toy_B(), device=device)

    def step(self, S: Any, A: Any, k: int) -> Any:
        return S @ self._A.to(S.dtype).T + A @ self._B.to(S.dtype).T

    def violations(self, S: Any, k: int) -> Any:
        return (S[:, :3].norm(dim=-1) < 1.0).to(S.dtype)


def _toy_A() -> np.ndarray:
    return np.block([[np.eye(3), TOY_DT * np.eye(3)], [np.zeros((3, 3)), np.eye(3)]])


def _toy_B() -> np.ndarray:
    return np.vstack([0.5 * TOY_DT**2 * np.eye(3), TOY_DT * np.eye(3)])


@register
class ToyScenario(Scenario):
    name: ClassVar[str] = "toy"
    version: ClassVar[str] = "0.1"
    n_steps: ClassVar[int] = TOY_STEPS
    cost_norm = "l1"
    scp: ClassVar[SCPSettings] = SCPSettings(tr_start=1.0, tr_end=0.01)
    mpc: ClassVar[MPCWeights] = MPCWeights(fuel=1.0, end=10.0, target=1.0, dist=(1,) * 6)
    state_labels = ("x", "y", "z", "vx", "vy", "vz")
    control_labels = ("ux", "uy", "uz")

    def sample(self, rng: np.random.Generator) -> Problem:
        x0 = np.concatenate([rng.uniform(-3, 3, 3), np.zeros(3)])
        goal = np.concatenate([rng.uniform(-3, 3, 3), np.zeros(3)])
        return Problem(x0=x0, goal=goal, dt=TOY_DT, n_steps=TOY_STEPS)

    def step(self, problem: Problem, k: int, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return x @ _toy_A().T + u @ _toy_B().T

    def convex_model(self, problem: Problem, window: Window, X_ref: np.ndarray, U_ref: np.ndarray) -> Any:
        raise NotImplementedError

    def constraints(self, problem: Problem, window: Window, X_ref: Any, U_ref: Any, *, obstacles: bool) -> list:
        return []

    def violations(self, problem: Problem, X: np.ndarray, start: int = 0) -> np.ndarray:
        return (np.linalg.norm(X[:, :3], axis=-1) < 1.0).astype(int)

    def path_violation(
        self, problem: Problem, X: np.ndarray, U: np.ndarray, window: Window, *, obstacles: bool = True
    ) -> float:
        return 0.0

    def batched_model(self, problems: Sequence[Problem], device: Any = "cpu") -> _ToyTorch:
        return _ToyTorch(device)

    def problem_from_features(self, x0: np.ndarray, goal: np.ndarray, dt: float, features: dict) -> Problem:
        return Problem(x0=x0, goal=goal, dt=dt, n_steps=TOY_STEPS)

    def to_model_states(self, problem: Problem, X: np.ndarray, start: int = 0) -> np.ndarray:
        # A non-identity representation map, so tests notice a missing from_model_states.
        return np.asarray(X, dtype=np.float64) * 2.0

    def from_model_states(self, problem: Problem, S: np.ndarray, start: int = 0) -> np.ndarray:
        return np.asarray(S, dtype=np.float64) / 2.0


@pytest.fixture
def toy() -> ToyScenario:
    return ToyScenario()


@pytest.fixture
def toy_stats() -> NormStats:
    return helpers.toy_stats()


@pytest.fixture
def wandb_offline(tmp_path: Any, monkeypatch: pytest.MonkeyPatch) -> Any:
    """wandb in offline mode with every directory it writes to under tmp_path."""
    root = tmp_path / "wandb-home"
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.delenv("WANDB_API_KEY", raising=False)
    for var in ("WANDB_DIR", "WANDB_CACHE_DIR", "WANDB_DATA_DIR", "WANDB_CONFIG_DIR"):
        path = root / var.lower()
        path.mkdir(parents=True)
        monkeypatch.setenv(var, str(path))
    monkeypatch.setenv("WANDB_SILENT", "true")
    return root
