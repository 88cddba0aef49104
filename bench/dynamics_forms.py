"""What the dynamics written once cost (``ttompc.scenarios.dynamics``), against hand-written forms in the same run.

Per built-in scenario, the median time of one call, in µs, and the ratio derived / hand-written (below 1: the
derived form is faster):

* ``numpy_step_1``, ``numpy_step_100``: the vectorised NumPy step (the free-flyer's ``Scenario.step``; the
  quadrotor's before it derived its own, written out below) against ``CompiledStep.step`` on 1 and 100 states;
* ``linearise``: the hand-written linearisation (``Scenario.convex_model``) against ``CompiledStep.linearise``
  (complex steps) on a 100-step window;
* ``torch_step_1``, ``torch_step_40``: the derived batched float32 step (``CompiledBatchedModel``) against the torch
  code it replaced (written out below; the free-flyer keeps it), at B = 1 and 40.

    python bench/dynamics_forms.py [--repeats 2000] [--out bench/results/dynamics_forms.json]
"""

from __future__ import annotations

import argparse
import functools
import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from record import Machine, result_path, write_result

from ttompc.scenarios import get_scenario
from ttompc.scenarios.base import Problem, Window


def per_call_us(fn: Callable[[], Any], repeats: int) -> float:
    """The median over 5 rounds of the mean time of one call, in µs (after one warm-up call)."""
    fn()
    rounds = []
    for _ in range(5):
        start = time.perf_counter()
        for _ in range(repeats):
            fn()
        rounds.append((time.perf_counter() - start) / repeats * 1e6)
    return statistics.median(rounds)


def torch_reference(name: str, problems: list[Problem]) -> Callable[[Any, Any, int], Any]:
    """The batched torch step each scenario had before its dynamics were written once."""
    sc = get_scenario(name)
    if name == "freeflyer":
        from ttompc.scenarios.freeflyer import A_STEP, B_IMP

        A, B = torch.as_tensor(A_STEP), torch.as_tensor(B_IMP)
        return lambda S, U, k: (S + U @ B.to(S.dtype).T) @ A.to(S.dtype).T
    if name == "quadrotor":
        from ttompc.scenarios.quadrotor import DRAG, MASS

        dt = torch.as_tensor([p.dt for p in problems])[:, None]

        def quadrotor(S: Any, U: Any, k: int) -> Any:
            v = S[:, 3:]
            dv = U / MASS - (DRAG / MASS) * torch.linalg.norm(v, dim=-1, keepdim=True) * v
            return S + dt.to(S.dtype) * torch.cat([v, dv], dim=-1)

        return quadrotor
    from ttompc.scenarios.rpod import orbit_matrices

    mats = [orbit_matrices(p) for p in problems]
    M = torch.as_tensor(np.stack([m.psi[1:] @ m.phi @ m.psi_inv[:-1] for m in mats]))
    N = torch.as_tensor(np.stack([m.psi[1:] @ m.phi @ m.B for m in mats]))
    assert sc.name == "rpod"
    return lambda S, U, k: (M[:, k].to(S.dtype) @ S[..., None] + N[:, k].to(S.dtype) @ U[..., None])[..., 0]


def quadrotor_step(problem: Problem, k: int, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The quadrotor's vectorised NumPy step before its dynamics were written once."""
    from ttompc.scenarios.quadrotor import DRAG, MASS

    v = x[..., 3:]
    dv = u / MASS - (DRAG / MASS) * np.linalg.norm(v, axis=-1, keepdims=True) * v
    return x + problem.dt * np.concatenate([v, dv], axis=-1)


def measure(name: str, repeats: int) -> dict[str, dict[str, float]]:
    sc = get_scenario(name)
    rng = np.random.default_rng(0)
    p = sc.sample(rng)
    su, sx = sc.control_units(), sc.state_units()
    U = rng.normal(size=(100, sc.control_dim)) * su
    X = sc.rollout(p, U) + rng.normal(size=(101, sc.state_dim)) * sx * 0.1
    out: dict[str, dict[str, float]] = {}

    def pair(key: str, hand: Callable[[], Any], derived: Callable[[], Any]) -> None:
        h, d = per_call_us(hand, repeats), per_call_us(derived, repeats)
        out[key] = {"hand_us": round(h, 2), "derived_us": round(d, 2), "ratio": round(d / h, 3)}

    dynamics = getattr(sc, "dynamics", None)
    if dynamics is not None:  # free-flyer, quadrotor: their exact step written once
        step = quadrotor_step if name == "quadrotor" else sc.step
        linearisation = sc.convex_model
        w = Window.full(p)
        assert np.allclose(dynamics.linearise(p, w, X, U).A, linearisation(p, w, X, U).A, rtol=1e-12, atol=1e-14)
        pair("numpy_step_1", lambda: step(p, 3, X[3], U[3]), lambda: dynamics.step(p, 3, X[3], U[3]))
        pair("numpy_step_100", lambda: step(p, 3, X[:100], U), lambda: dynamics.step(p, 3, X[:100], U))
        pair("linearise", lambda: linearisation(p, w, X, U), lambda: dynamics.linearise(p, w, X, U))
    for B in (1, 40):
        problems = [sc.sample(rng) for _ in range(B)]
        model = dynamics.batched(sc, problems) if dynamics is not None else sc.batched_model(problems)
        reference = torch_reference(name, problems)
        S = torch.as_tensor(rng.normal(size=(B, sc.state_dim)) * sx, dtype=torch.float32)
        A = torch.as_tensor(rng.normal(size=(B, sc.control_dim)) * su, dtype=torch.float32)
        assert torch.allclose(model.step(S, A, 5), reference(S, A, 5), rtol=1e-4, atol=1e-5)
        pair(f"torch_step_{B}", functools.partial(reference, S, A, 5), functools.partial(model.step, S, A, 5))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=2000)
    parser.add_argument("--out", default=str(result_path("dynamics_forms")))
    args = parser.parse_args()
    torch.set_num_threads(1)
    machine = Machine()
    result: dict[str, Any] = {name: measure(name, args.repeats) for name in ("freeflyer", "quadrotor", "rpod")}
    result["machine"] = machine.record()
    write_result(result, args.out)


if __name__ == "__main__":
    main()
