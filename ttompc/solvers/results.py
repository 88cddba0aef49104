"""What an SCP solve returns: status, per-iteration history and the returned iterate, plus the soft terminal term
of receding-horizon windows. Kept apart from the loop (``engine.py``) and the public entry points (``scp.py``)
so that neither has to import the other."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from ttompc.scenarios.base import Window


class SCPStatus(str, enum.Enum):
    OPTIMAL = "optimal"  # stopping rule met by a feasible iterate
    FEASIBLE = "feasible"  # iteration cap reached; best iterate satisfies the nonlinear constraints
    INFEASIBLE = "infeasible"  # no iterate satisfies the nonlinear constraints within tolerance
    SOLVER_ERROR = "solver_error"  # the convex solver failed numerically on the first subproblem


@dataclass
class IterateRecord:
    iteration: int
    cost: float  # Σ c(u_k) of the iterate (unweighted stage cost)
    objective: float  # subproblem objective value (incl. terminal terms and penalties)
    violation: float  # max violation of the nonlinear constraints at the iterate
    step: float  # max_k ‖x_k − x̄_k‖₂ (distance from the previous reference)
    trust_radius: float
    solver_time: float  # raw convex solve time (s)
    solver_status: str


@dataclass
class SCPResult:
    status: SCPStatus
    X: np.ndarray  # (H+1, n) states of the returned (best feasible, else least-violating) iterate
    U: np.ndarray  # (H, m)
    cost: float
    violation: float
    iterations: int  # number of convex subproblems solved
    solve_time: float  # wall time of the whole solve (s)
    solver_time: float  # sum of raw convex solve times (s)
    window: Window
    history: list[IterateRecord] = field(default_factory=list)
    best_iteration: int = -1

    @property
    def success(self) -> bool:
        return self.status in (SCPStatus.OPTIMAL, SCPStatus.FEASIBLE)

    def __repr__(self) -> str:
        """One line: ``print(result)`` in a session must not dump the trajectory and the history."""
        return (
            f"SCPResult({self.status.value}, cost={self.cost:.6g}, iterations={self.iterations}, "
            f"violation={self.violation:.2g}, X{self.X.shape}, U{self.U.shape}, solve_time={self.solve_time:.3g}s)"
        )

    def summary(self) -> dict[str, float | int | str]:
        return {
            "status": self.status.value,
            "cost": self.cost,
            "iterations": self.iterations,
            "solve_time": self.solve_time,
            "solver_time": self.solver_time,
            "violation": self.violation,
        }


@dataclass(frozen=True, init=False)
class TerminalCost:
    """Soft terminal term ‖diag(weights) (x_{t+H} − target)‖₂ replacing the terminal equality (MPC)."""

    target: np.ndarray  # (n,)
    weights: np.ndarray  # (n,); a scalar given to the constructor weighs every state alike

    def __init__(self, target: ArrayLike, weights: ArrayLike) -> None:
        object.__setattr__(self, "target", np.asarray(target, dtype=np.float64))
        object.__setattr__(self, "weights", np.broadcast_to(np.asarray(weights, float), self.target.shape))

    def __call__(self, x: np.ndarray) -> float:
        """The term's value at the window's last state ``x``."""
        return float(np.linalg.norm(self.weights * (np.asarray(x) - self.target)))
