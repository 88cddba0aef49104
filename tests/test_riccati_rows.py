"""The Riccati kernel's constraint passes (``riccati_rows``): its boxes' own passes are its rows' of width 1 to the
bit, and two-sided boxes (l = u, one side only, bounds that never bind, hard and soft) reach an independent cvxpy
model's optimum."""

from __future__ import annotations

import cvxpy as cp
import numpy as np
import pytest

from ttompc.solvers.backends.riccati_qp import Boxes, Dynamics, RiccatiOptions, Rows, StageCost, StageQPData

N, NX, NU = 8, 3, 2
TIGHT = RiccatiOptions(tol=1e-10, gap_tol=1e-11, max_iter=100)


def _qp(seed: int, boxes: Boxes, rows: Rows | None = None) -> StageQPData:
    """A random stage QP (N stages, NX states, NU controls) under ``boxes`` and ``rows`` (none by default)."""
    rng = np.random.default_rng(seed)
    A = np.eye(NX) + 0.1 * rng.normal(size=(N, NX, NX))
    dyn = Dynamics(A, rng.normal(size=(N, NX, NU)), 0.1 * rng.normal(size=(N, NX)), rng.normal(size=NX))
    cost = StageCost(rng.uniform(0.5, 2.0, size=(N + 1, NX + NU)), rng.normal(size=(N + 1, NX + NU)))
    return StageQPData(dyn, cost, boxes, Rows.none() if rows is None else rows)


def _two_sided() -> tuple[Boxes, dict]:
    """Two-sided boxes l ≤ y ≤ u as the engine lays them out (the upper sides, then the lower ones: −y ≤ −l): hard
    |x_0| ≤ 0.3 (binding), soft u_0 = 0.2 (l = u, penalty 0.8), hard x_1 ≤ 0.1 alone (l = −∞: no lower side), and
    hard |u_1| ≤ 50 (never binding). Returns the boxes and, per (column, hard), the bounds (l, u)."""
    ks, cols, signs, d, rho = [], [], [], [], []
    spec = {(0, True): (-0.3, 0.3), (NX, False): (0.2, 0.2), (1, True): (-np.inf, 0.1), (NX + 1, True): (-50.0, 50.0)}
    for side in (0, 1):
        for (j, hard), (low, high) in spec.items():
            bound = high if side == 0 else -low
            if not np.isfinite(bound):
                continue
            stages = range(1, N + 1) if j < NX else range(N)
            ks += list(stages)
            cols += [j] * len(stages)
            signs += [-1.0 if side else 1.0] * len(stages)
            d += [bound] * len(stages)
            rho += [0.0 if hard else 0.8] * len(stages)
    boxes = Boxes(np.array(ks), np.array(cols), np.array(signs), np.array(d), np.array(rho))
    return boxes, spec


def _solve(qp: StageQPData) -> tuple[tuple, np.ndarray, np.ndarray]:
    """The kernel's solve of ``qp`` from y = 0, π = 0: (result, y, π)."""
    from ttompc.solvers.backends.riccati_kernel import solve

    y, pi = np.zeros((N + 1, NX + NU)), np.zeros((N, NX))
    return tuple(solve(qp, y, pi, TIGHT)), y, pi


@pytest.mark.parametrize("seed", [0, 1])
def test_boxes_are_rows_of_width_one_to_the_bit(seed) -> None:
    """The same constraints as boxes or as rows of width 1 (coefficient ±1): the same status, iterations, residual,
    gap and iterates, bit for bit."""
    boxes, _ = _two_sided()
    as_rows = Rows(boxes.k, boxes.j.reshape(-1, 1), boxes.sign.reshape(-1, 1), boxes.d, boxes.rho)
    out_b, y_b, pi_b = _solve(_qp(seed, boxes))
    out_r, y_r, pi_r = _solve(_qp(seed, Boxes.none(), as_rows))
    assert out_b[0] == 0, out_b
    assert out_b == out_r
    assert np.array_equal(y_b, y_r) and np.array_equal(pi_b, pi_r)


@pytest.mark.parametrize("seed", [0, 1])
def test_two_sided_boxes_reach_the_cvxpy_optimum(seed) -> None:
    """Two-sided boxes (l = u soft, one side infinite, never binding, binding): cvxpy's optimum of l ≤ y ≤ u (the hard
    ones) and ρ·dist(y, [l, u]) (the soft one), and the hard bounds hold."""
    boxes, spec = _two_sided()
    qp = _qp(seed, boxes)
    out, y, _ = _solve(qp)
    assert out[0] == 0, out
    dyn, cost = qp.dynamics, qp.cost
    Y = cp.Variable((N + 1, NX + NU))
    cons = [Y[0, :NX] == dyn.x0, Y[N, NX:] == 0]
    cons += [Y[k + 1, :NX] == dyn.A[k] @ Y[k, :NX] + dyn.B[k] @ Y[k, NX:] + dyn.c[k] for k in range(N)]
    obj = 0.5 * cp.sum(cp.multiply(cost.Qd, cp.square(Y))) + cp.sum(cp.multiply(cost.q, Y))
    for (j, hard), (low, high) in spec.items():
        v = Y[1:, j] if j < NX else Y[:N, j]
        if hard:
            cons += [v <= high] + ([v >= low] if np.isfinite(low) else [])
        else:
            obj += 0.8 * cp.sum(cp.pos(v - high) + cp.pos(low - v))
    problem = cp.Problem(cp.Minimize(obj), cons)
    problem.solve(solver=cp.CLARABEL, tol_gap_abs=1e-10, tol_gap_rel=1e-10, tol_feas=1e-10)
    assert problem.status == cp.OPTIMAL
    assert qp.objective(y) == pytest.approx(problem.value, rel=1e-6)
    assert Y.value is not None
    np.testing.assert_allclose(y, Y.value, atol=1e-5)
    assert np.max(np.abs(y[1:, 0])) <= 0.3 + 1e-9 and np.max(y[1:, 1]) <= 0.1 + 1e-9
    assert np.isclose(np.max(np.abs(y[1:, 0])), 0.3) or np.isclose(np.max(y[1:, 1]), 0.1)  # a hard bound binds
