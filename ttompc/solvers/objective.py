"""The objective ½ z̃ᵀP z̃ + qᵀz̃ (+ a constant) of the conic assembly (``subproblem.AssembledSubproblem``), in its
column-scaled variables z = S z̃: the quadratic stage cost's diagonal and, where the spec has a terminal cost-to-go
model (``SubproblemSpec.terminal_value``), that model's dense block on the window's last state.

P's sparsity pattern is fixed by the spec (Clarabel updates values in place, so a pattern must not change between
iterations): the block's upper triangle is allocated at assembly, explicit zeros included, and each iteration only
rewrites its values and the linear term from ``SubproblemData.terminal_cost`` (``ConicObjective.values``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import scipy.sparse as sp

if TYPE_CHECKING:
    from ttompc.solvers.spec import QuadraticTerminalCost, SubproblemSpec


class ConicValues(NamedTuple):
    """One iteration's numbers of the assembled conic program; every pattern is fixed by the spec."""

    A: np.ndarray  # values of the column-scaled constraint matrix, in its CSC order (``AssembledSubproblem.matrix``)
    b: np.ndarray  # (n_con,)
    P: np.ndarray  # values of the column-scaled P's upper triangle, in its CSC order (``ConicObjective.matrix``)
    q: np.ndarray  # (n_var,) the column-scaled linear cost
    offset: float  # the objective's constant (the terminal model's), which ½ z̃ᵀP z̃ + qᵀz̃ leaves out


class ConicObjective:
    """The upper triangle of P (CSC, fixed pattern) and the linear cost q of one structure.

    ``scale`` (n_var,): the variables' units S; ``q`` (n_var,): the constant linear cost, already scaled; ``last``
    (n,): the indices of x_H; ``controls``: the indices of the controls (the quadratic stage cost's diagonal)."""

    def __init__(
        self, spec: SubproblemSpec, scale: np.ndarray, q: np.ndarray, last: np.ndarray, controls: np.ndarray
    ) -> None:
        self.q = q
        self.last, self.sx = last, scale[last]
        empty = np.zeros(0, np.int64)
        u = controls.ravel() if spec.cost_norm == "quad" else empty  # ½ w‖u‖²: a diagonal on the controls
        self.tri = np.triu_indices(spec.n) if spec.terminal_value else (empty, empty)
        r = np.concatenate([u, last[self.tri[0]]])
        c = np.concatenate([u, last[self.tri[1]]])
        v = np.concatenate([spec.fuel_weight * scale[u] ** 2, np.zeros(len(self.tri[0]))])
        order = np.lexsort((r, c))  # CSC order
        self._indices = r[order].astype(np.int64)
        self._indptr = np.concatenate([[0], np.cumsum(np.bincount(c, minlength=len(scale)))]).astype(np.int64)
        self._base = v[order]
        where = np.empty(len(order), np.int64)  # where each entry sits in the CSC values
        where[order] = np.arange(len(order))
        self._block = where[len(u) :]  # the block's entries, in ``tri`` order
        self.shape = (len(scale), len(scale))

    def matrix(self, values: np.ndarray) -> sp.csc_matrix:
        """P's upper triangle with ``values`` (``ConicValues.P``) in its fixed pattern (explicit zeros kept)."""
        return sp.csc_matrix((values, self._indices, self._indptr), shape=self.shape)

    def values(self, terminal: QuadraticTerminalCost | None) -> tuple[np.ndarray, np.ndarray, float]:
        """(P values, q, constant) with the terminal model ½(x − x̄)ᵀM(x − x̄) + gᵀ(x − x̄) on x_H (state units) in
        the scaled x̃ = x / sx: the block S M S (symmetrised), the linear term S(g − M x̄) and the constant
        ½ x̄ᵀM x̄ − gᵀx̄. Without a model (or a spec without the block) the stage cost's alone; a model given to a
        spec without the block is a ``ValueError``: it would be dropped without a word."""
        if terminal is None or not len(self.tri[0]):
            if terminal is not None:
                raise ValueError("a terminal cost-to-go model needs a spec with terminal_value=True")
            return self._base, self.q, 0.0
        M = np.asarray(terminal.hessian, np.float64)
        M = 0.5 * (M + M.T)
        g, center = np.asarray(terminal.gradient, np.float64), np.asarray(terminal.center, np.float64)
        p = self._base.copy()
        p[self._block] = (self.sx[:, None] * M * self.sx[None, :])[self.tri]
        q = self.q.copy()
        q[self.last] += self.sx * (g - M @ center)
        return p, q, 0.5 * float(center @ M @ center) - float(g @ center)
