"""``ttompc.scenarios.dynamics``: the forms a ``CompiledStep`` derives from one step function agree with the
hand-written ones the built-in scenarios keep (an independent implementation of the same physics; the quadrotor's
derived step is checked against its ODE in tests/test_quadrotor.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ttompc.scenarios import get_scenario
from ttompc.scenarios.base import Window


def test_the_derived_step_is_the_numpy_step() -> None:
    sc = get_scenario("freeflyer")
    p = sc.sample(np.random.default_rng(0))
    rng = np.random.default_rng(1)
    X, U = rng.normal(size=(5, 6)) * 0.3, rng.normal(size=(5, 3)) * 0.05
    derived = sc.dynamics.step(p, 7, X, U)
    np.testing.assert_allclose(derived, sc.step(p, 7, X, U), rtol=1e-14, atol=1e-15)
    # leading axes broadcast as NumPy's: one control for every state, one state alone
    np.testing.assert_allclose(sc.dynamics.step(p, 7, X, U[0]), sc.step(p, 7, X, U[0]), rtol=1e-14, atol=1e-15)
    assert sc.dynamics.step(p, 7, X[0], U[0]).shape == (6,)


@pytest.mark.parametrize("name", ["freeflyer", "quadrotor"])
def test_the_derived_linearisation_is_the_hand_written_one(name: str) -> None:
    """Complex-step Jacobians equal the analytic ones to rounding, away from any consistent trajectory too."""
    sc = get_scenario(name)
    p = sc.sample(np.random.default_rng(0))
    rng = np.random.default_rng(2)
    w = Window(40, 30, p.n_steps)
    X, U = rng.normal(size=(31, 6)) * 0.3, rng.normal(size=(30, 3)) * 0.05
    got, ref = sc.dynamics.linearise(p, w, X, U), sc.convex_model(p, w, X, U)
    for part in ("A", "B", "c"):
        np.testing.assert_allclose(getattr(got, part), getattr(ref, part), rtol=1e-12, atol=1e-14, err_msg=part)


def test_the_batched_model_keeps_dtype_and_steps_each_problem_with_its_row() -> None:
    sc = get_scenario("rpod")  # time-varying, per-problem rows
    problems = [sc.sample(np.random.default_rng(s)) for s in (3, 4)]
    model = sc.batched_model(problems)
    rng = np.random.default_rng(5)
    S, A = torch.as_tensor(rng.normal(size=(2, 6)) * 50), torch.as_tensor(rng.normal(size=(2, 3)) * 0.01)
    for k in (0, 57):
        got = model.step(S, A, k)
        assert got.dtype == torch.float64
        for b, p in enumerate(problems):
            x = sc.from_model_states(p, S[b : b + 1].numpy(), start=k)[0]
            want = sc.to_model_states(p, sc.step(p, k, x, A[b].numpy())[None], start=k + 1)[0]
            np.testing.assert_allclose(got[b].numpy(), want, rtol=1e-9, atol=1e-9)
        assert model.step(S.float(), A.float(), k).dtype == torch.float32
