"""Scenarios with one planted mistake each, loaded by file spec in the ``check-scenario`` tests: subclasses of the
worked example (examples/di2d.py) that a user could plausibly have written."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ttompc.scenarios import ConvexModel, Problem, Window, get_scenario
from ttompc.scenarios.dynamics import CompiledStep

EXAMPLE = f"{Path(__file__).resolve().parents[1] / 'examples' / 'di2d.py'}:DoubleIntegrator2D"
DoubleIntegrator2D: Any = type(get_scenario(EXAMPLE))


class WrongJacobian(DoubleIntegrator2D):
    """A 'linearisation' whose slope ∂p_x+/∂v_x is 2·dt instead of dt, made exact at the reference through c: the
    model reproduces step() where it was built, so only the finite-difference check sees the wrong derivative."""

    name = "di2d-wrong-jacobian"
    exact_linear_dynamics = False  # it is not: A and c now depend on the reference

    def convex_model(self, problem: Problem, window: Window, X_ref: np.ndarray, U_ref: np.ndarray) -> ConvexModel:
        model = super().convex_model(problem, window, X_ref, U_ref)
        model.A[:, 0, 2] *= 2.0
        H = window.length
        exact = self.step_window(problem, window.start, X_ref[:H], U_ref)
        model.c = exact - np.einsum("jab,jb->ja", model.A, X_ref[:H]) - np.einsum("jab,jb->ja", model.B, U_ref)
        return model


class WrongBatchedModel(DoubleIntegrator2D):
    """A hand-written torch model that forgets the ½ of ½·dt²·u in the position update."""

    name = "di2d-wrong-batched-model"

    def batched_model(self, problems: Sequence[Problem], device: Any = "cpu") -> Any:
        model = super().batched_model(problems, device)
        exact = model.step

        def step(S: Any, A: Any, k: int) -> Any:
            out = exact(S, A, k).clone()
            out[:, :2] += 0.5 * problems[0].dt ** 2 * A
            return out

        model.step = step
        return model


def forgetful_step(x: Any, u: Any, k: int, p: Any, out: Any) -> None:
    """The example's step without the ½ of ½·dt²·u."""
    dt = p[0]
    for i in range(2):
        out[i] = x[i] + dt * x[2 + i] + dt * dt * u[i]
        out[2 + i] = x[2 + i] + dt * u[i]


class WrongCompiledStep(DoubleIntegrator2D):
    """The exact step in numpy, but compiled dynamics (the convex model's, the rollout's and the fused decoder's)
    without the ½."""

    name = "di2d-wrong-compiled-step"
    dynamics = CompiledStep(forgetful_step)

    def step(self, problem: Problem, k: int, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        dt = problem.dt
        x, u = np.asarray(x), np.asarray(u)
        return np.concatenate([x[..., :2] + dt * x[..., 2:] + 0.5 * dt**2 * u, x[..., 2:] + dt * u], axis=-1)


class UnsolvableSampler(DoubleIntegrator2D):
    """Goals 60 m away: with |a| <= 1 m/s² for 10 s no trajectory gets further than 25 m, REL included."""

    name = "di2d-unsolvable-sampler"

    def sample(self, rng: np.random.Generator) -> Problem:
        problem = super().sample(rng)
        goal = problem.goal + np.array([60.0, 0.0, 0.0, 0.0])
        return Problem(x0=problem.x0, goal=goal, dt=problem.dt, n_steps=problem.n_steps)


class WrongTrustNorm(DoubleIntegrator2D):
    """A trust-region norm the engine does not have."""

    name = "di2d-wrong-trust-norm"
    trust_norm = "l1"  # type: ignore[assignment]


class NegativePerturbation(DoubleIntegrator2D):
    """A perturbed plant with a negative noise level (a sign slip): refused by the interface check."""

    name = "di2d-negative-perturbation"
    perturbation = (0.05, -0.02, 0.002)


class NoDynamics(DoubleIntegrator2D):
    """A ``CompiledScenario`` that forgot to declare its step function."""

    name = "di2d-no-dynamics"
    dynamics = None
