"""The naive baseline: the same convex subproblem written as a fresh cvxpy problem from per-timestep constraint
lists at every SCP iteration, as the reference code does. It is slow on purpose (cvxpy compiles the problem every
time) and independent of the sparse assembly, which makes it the ground truth for tests and the baseline of
``bench/solver_speed.py``. Selected with ``backend="cvxpy-naive"``."""

from __future__ import annotations

import time
from typing import Any

import cvxpy as cp
import numpy as np

from ttompc.scenarios.base import BlockKind
from ttompc.solvers.backends.base import BackendSolution
from ttompc.solvers.spec import SubproblemData, SubproblemSpec


class NaiveCvxpySolver:
    def __init__(self, spec: SubproblemSpec, solver: str = "CLARABEL") -> None:
        self.spec = spec
        self.solver = solver

    def restart(self) -> None:
        """Nothing to forget: the problem is rebuilt for every solve."""

    def solve(self, data: SubproblemData) -> tuple[np.ndarray | None, np.ndarray | None, BackendSolution]:
        t0 = time.perf_counter()
        spec = self.spec
        H, n, m = spec.H, spec.n, spec.m
        x = [cp.Variable(n) for _ in range(H + 1)]
        u = [cp.Variable(m) for _ in range(H)]
        cons = [x[0] == data.x_start]
        cost: Any = 0  # a cvxpy expression once terms are added
        if spec.cost_norm == "l1":
            cost += spec.fuel_weight * sum(cp.norm1(u[j]) for j in range(H))
        elif spec.cost_norm == "l2":
            cost += spec.fuel_weight * sum(cp.norm(u[j], 2) for j in range(H))
        else:
            cost += 0.5 * spec.fuel_weight * sum(cp.sum_squares(u[j]) for j in range(H))
        for j in range(H):
            rhs = data.model.A[j] @ x[j] + data.model.B[j] @ u[j] + data.model.c[j]
            if spec.virtual_control:
                rows = spec.virtual_rows()
                nu = cp.Variable(len(rows))
                cost += spec.penalty * cp.norm1(nu)
                rhs = rhs + np.eye(n)[:, rows] @ nu
            cons.append(x[j + 1] == rhs)
        if spec.end_form == "hard":
            if spec.penalized:
                s = cp.Variable(n)
                cost += spec.penalty * cp.norm1(s)
                cons.append(x[H] - s == data.goal)
            else:
                cons.append(x[H] == data.goal)
        elif spec.end_form == "soft":
            cost += cp.norm(cp.multiply(data.terminal_weights, x[H] - data.terminal_target), 2)
        if data.terminal_cost is not None:  # ½ eᵀPe + gᵀe, e = x_H − x̄ (P positive semidefinite)
            tc = data.terminal_cost
            e = x[H] - tc.center
            cost += 0.5 * cp.quad_form(e, cp.psd_wrap(0.5 * (tc.hessian + tc.hessian.T))) + tc.gradient @ e
        for block in data.blocks:
            for kk, k in enumerate(block.steps):
                expr = block.Gx[kk] @ x[k]
                if block.Gu is not None:
                    expr = expr + block.Gu[kk] @ u[k]
                if block.kind is BlockKind.SOC:
                    cons.append(cp.norm(expr[1:] - block.h[kk, 1:], 2) <= expr[0] - block.h[kk, 0])
                elif block.kind is BlockKind.EQ and spec.soft_equalities:
                    cost += block.weight * cp.norm(expr - block.h[kk], 2)
                elif block.kind is BlockKind.EQ:
                    if spec.penalized:
                        s = cp.Variable(block.rows_per_step)
                        cost += spec.penalty * cp.norm1(s)
                        cons.append(expr - s == block.h[kk])
                    else:
                        cons.append(expr == block.h[kk])
                else:
                    slack: Any = 0  # a cvxpy variable for soft rows
                    if spec.penalized and block.soft:
                        slack = cp.Variable(block.rows_per_step, nonneg=True)
                        cost += spec.penalty * cp.sum(slack)
                    cons.append(expr - slack <= block.h[kk])
                    if block.lower is not None:
                        cons.append(expr + slack >= block.lower[kk])
        for j in spec.tr_states:
            if spec.trust == "l2":
                cons.append(cp.norm(x[j] - data.X_ref[j], 2) <= data.delta)
            elif spec.trust == "linf":
                cons.append(cp.norm(x[j] - data.X_ref[j], "inf") <= data.delta)
        prob = cp.Problem(cp.Minimize(cost), cons)
        prob.solve(solver=self.solver)
        elapsed = time.perf_counter() - t0
        ok = prob.status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE)
        sol = BackendSolution(
            None, float(prob.value) if ok else np.inf, ok, prob.status == cp.INFEASIBLE, str(prob.status), elapsed
        )
        if not ok:
            return None, None, sol
        return np.stack([np.asarray(xi.value) for xi in x]), np.stack([np.asarray(ui.value) for ui in u]), sol
