"""What an SCP solve returns: status, per-iteration history and the returned iterate, plus the soft terminal term
of receding-horizon windows. Kept apart from the loop (``engine.py``) and the public entry points (``scp.py``)
so that neither has to import the other."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Protocol

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
    # (H+1, n): λ_k = ∂J*/∂x_k of the returned iterate's convex subproblem, the gradient of the window's optimal
    # cost-to-go from x_k (k ≥ 1; row 0 NaN), where the backend gives multipliers (the riccati kernel, QOCO,
    # Clarabel); else None
    costates: np.ndarray | None = None

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


class LocalModel(Protocol):
    """A cost-to-go's value, gradient (n,) and positive semidefinite Hessian (n, n) at one state."""

    @property
    def value(self) -> float: ...

    @property
    def gradient(self) -> np.ndarray: ...

    @property
    def hessian(self) -> np.ndarray: ...


class TerminalValue(Protocol):
    """A cost-to-go J(x) of a window's last state (e.g. a model's value output at the window's end step): its value,
    and a convex local model about a state that each SCP iteration re-expands about its reference."""

    def __call__(self, x: np.ndarray) -> float: ...

    def expand(self, x: np.ndarray) -> LocalModel: ...


@dataclass(frozen=True, init=False)
class TerminalCost:
    """Soft terminal term replacing the terminal equality (MPC): ‖diag(weights) (x_{t+H} − target)‖₂ (the paper's;
    all-zero weights: none) plus, where given, a cost-to-go ``value`` J(x_{t+H}) that each SCP iteration models by
    its local quadratic about the iteration's reference (``TerminalValue``). J is in the stage cost's units (an
    optimum's cost-to-go): the window weighs it as it weighs its stage cost (``SCPProblem.fuel_weight``, ``mpc.fuel``
    in soft mode), while the norm term's weights are the window's own."""

    target: np.ndarray  # (n,)
    weights: np.ndarray  # (n,); a scalar given to the constructor weighs every state alike
    value: TerminalValue | None

    def __init__(self, target: ArrayLike, weights: ArrayLike, value: TerminalValue | None = None) -> None:
        object.__setattr__(self, "target", np.asarray(target, dtype=np.float64))
        object.__setattr__(self, "weights", np.broadcast_to(np.asarray(weights, float), self.target.shape))
        object.__setattr__(self, "value", value)
        if value is None and not self.weights.any():
            raise ValueError("a terminal cost needs weights > 0 or a value")

    @property
    def has_norm(self) -> bool:
        """Whether the 2-norm term is present (some weight > 0)."""
        return bool(self.weights.any())

    def __call__(self, x: np.ndarray, value_weight: float = 1.0) -> float:
        """The term's value at the window's last state ``x``, its cost-to-go weighted by ``value_weight`` (the
        window's stage-cost weight)."""
        norm = float(np.linalg.norm(self.weights * (np.asarray(x) - self.target)))
        return norm if self.value is None else norm + value_weight * self.value(np.asarray(x))
