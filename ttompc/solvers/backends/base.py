"""What every subproblem solver of the SCP engine provides (``SubproblemSolver``), the solution it returns
(``BackendSolution``) and the fallback that takes the subproblems a primary solver fails on (``Fallback``)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ttompc.scenarios.base import BlockKind
from ttompc.solvers.spec import SubproblemData, SubproblemSpec


@dataclass
class BackendSolution:
    z: np.ndarray | None
    objective: float
    ok: bool  # a usable (optimal or almost optimal) primal solution
    infeasible: bool  # the solver certified primal infeasibility
    status: str
    solve_time: float
    # (H, n): the dynamics multipliers, ∂(subproblem optimum)/∂x_k for k = 1..H per unit of the state, where the
    # backend gives them (the riccati kernel, QOCO, Clarabel); None elsewhere (PIQP, cvxpy-naive)
    costates: np.ndarray | None = None


class SubproblemSolver(Protocol):
    def solve(self, data: SubproblemData) -> tuple[np.ndarray | None, np.ndarray | None, BackendSolution]: ...

    def restart(self) -> None:
        """Make the next ``solve`` independent of the data solved before (see ``engine.run_scp``)."""


def is_qp(spec: SubproblemSpec) -> bool:
    """Whether ``spec`` has no second-order cone: a QP backend can solve it."""
    soft_eq = spec.soft_equalities and any(BlockKind(sig[1]) is BlockKind.EQ for sig in spec.blocks)
    return (
        spec.cost_norm in ("l1", "quad")
        and spec.trust in ("linf", "none")
        and spec.end_form == "hard"
        and not soft_eq
        and not any(BlockKind(sig[1]) is BlockKind.SOC for sig in spec.blocks)
    )


class Fallback:
    """The solver, built on first need, that takes the subproblems the primary backend could not solve."""

    def __init__(self, make: Callable[[], SubproblemSolver] | None) -> None:
        self._make = make
        self._solver: SubproblemSolver | None = None

    def restart(self) -> None:
        if self._solver is not None:
            self._solver.restart()

    def take(
        self, data: SubproblemData, failed: BackendSolution
    ) -> tuple[np.ndarray | None, np.ndarray | None, BackendSolution]:
        """The fallback's solution of ``data`` (status and time include the failed attempt); without a fallback,
        the failure itself."""
        if self._make is None:
            return None, None, failed
        if self._solver is None:
            self._solver = self._make()
        X, U, sol = self._solver.solve(data)
        sol.solve_time += failed.solve_time
        sol.status = f"{failed.status} -> {sol.status}"
        return X, U, sol


def cone_error(name: str) -> str:
    return (
        f"backend {name!r} solves QPs only, but this subproblem has second-order cones (2-norm cost, 2-norm trust "
        "region, approach cone or a soft terminal norm); use backend='auto', 'qoco' or 'clarabel'"
    )
