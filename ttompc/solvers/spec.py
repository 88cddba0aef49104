"""The convex SCP subproblem's key and data: ``SubproblemSpec`` (the structural key: two iterations with equal specs
share one matrix structure), ``SubproblemData`` (one iteration's values) and ``QuadraticTerminalCost`` (a convex
local model of a terminal cost-to-go on the window's last state). Every backend (``ttompc.solvers.backends``) and
the conic assembly (``subproblem.py``, ``objective.py``) read them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from ttompc.scenarios.base import ConstraintBlock, ConvexModel, units_of


class QuadraticTerminalCost(NamedTuple):
    """½ (x_H − x̄)ᵀ P (x_H − x̄) + gᵀ(x_H − x̄) on the window's last state, in the state's own units: a convex local
    model of a terminal cost-to-go about x̄."""

    hessian: np.ndarray  # (n, n) P, symmetric positive semidefinite
    gradient: np.ndarray  # (n,) g
    center: np.ndarray  # (n,) x̄


@dataclass
class SubproblemData:
    """Everything one SCP iteration feeds to the convex subproblem (values only; shapes are in the key)."""

    x_start: np.ndarray  # (n,) fixed initial state of the window
    model: ConvexModel
    blocks: list[ConstraintBlock]
    X_ref: np.ndarray  # (H+1, n) trust-region centre
    delta: float  # trust-region radius (inf: no trust region)
    goal: np.ndarray  # (n,) terminal state for a hard terminal condition
    terminal_target: np.ndarray | None  # (n,) x̄ for the soft terminal term
    terminal_weights: np.ndarray | None  # (n,) diagonal of P
    # added to the objective (the riccati kernel's dense block, the conic assembly's block in P where the spec has
    # ``terminal_value``); PIQP solves no window with a terminal term
    terminal_cost: QuadraticTerminalCost | None = None


@dataclass(frozen=True)
class SubproblemSpec:
    """The structural key: two iterations with equal specs share one matrix structure."""

    H: int
    n: int
    m: int
    cost_norm: str
    fuel_weight: float
    penalized: bool
    virtual_control: bool  # ν on the dynamics rows ``vc_rows`` (empty: all rows), with an exact L1 penalty
    trust: str  # "l2", "linf" or "none"
    # the window end's form: "hard" (x_H = goal), "soft" (the 2-norm term's cone) or "value" (a cost-to-go model alone)
    end_form: str
    soft_equalities: bool
    penalty: float
    blocks: tuple[tuple[Any, ...], ...]
    tr_states: tuple[int, ...] = ()  # window states under the trust region
    state_scale: tuple[float, ...] = ()  # characteristic magnitudes (non-dimensionalisation); empty = 1
    control_scale: tuple[float, ...] = ()
    model_masks: tuple[tuple[bool, ...], tuple[bool, ...]] | None = None  # flattened A/B masks (None: dense)
    vc_rows: tuple[int, ...] = ()
    # every iteration's data has a terminal cost-to-go model (``SubproblemData.terminal_cost``; always with "value"):
    # the conic assembly allocates its dense block in P
    terminal_value: bool = False

    def units(self) -> tuple[np.ndarray, np.ndarray]:
        """The state and control units of the non-dimensionalised variables (ones where no scale is given)."""
        return units_of(self.state_scale, self.n), units_of(self.control_scale, self.m)

    def virtual_rows(self) -> np.ndarray:
        """Dynamics rows that carry virtual control (those the convex model only approximates)."""
        return np.asarray(self.vc_rows or range(self.n), dtype=np.int64)

    @staticmethod
    def model_signature(model: ConvexModel) -> tuple[tuple[bool, ...], tuple[bool, ...]] | None:
        if model.A_mask is None and model.B_mask is None:
            return None
        n, m = model.B.shape[1:]
        A = np.ones((n, n), bool) if model.A_mask is None else np.asarray(model.A_mask, bool)
        B = np.ones((n, m), bool) if model.B_mask is None else np.asarray(model.B_mask, bool)
        return tuple(A.ravel().tolist()), tuple(B.ravel().tolist())

    @staticmethod
    def block_signature(block: ConstraintBlock) -> tuple[Any, ...]:
        """name, kind, steps, rows per step, has Gu, soft, weight, two-sided, Gx mask, Gu mask (None: dense)."""
        return (
            block.name,
            block.kind.value,
            tuple(np.asarray(block.steps).tolist()),
            block.rows_per_step,
            block.Gu is not None,
            bool(block.soft),
            float(block.weight),
            block.lower is not None,
            None if block.Gx_mask is None else tuple(np.asarray(block.Gx_mask, bool).ravel().tolist()),
            None if block.Gu_mask is None else tuple(np.asarray(block.Gu_mask, bool).ravel().tolist()),
        )


def structural_mask(flat: tuple[bool, ...] | None, shape: tuple[int, int]) -> np.ndarray:
    """A structural mask from its spec form (None: dense)."""
    return np.ones(shape, bool) if flat is None else np.asarray(flat, bool).reshape(shape)
