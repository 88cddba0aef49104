"""The convex SCP subproblem, assembled directly as sparse conic data and updated in place between iterations.

    min  ½ zᵀPz + qᵀz   s.t.  A z + s = b,  s ∈ {0}ⁿᶻ × ℝ₊ⁿⁿ × Q^{d₁} × … × Q^{dₖ}      (Clarabel's standard form)

z stacks the window states X (H+1, n), controls U (H, m), the cost epigraph variables and the slacks. The matrix
*structure* (sparsity, cone sizes) depends only on a key — window length, cost norm, formulation, trust-region norm,
end form and the shapes/steps of the scenario's constraint blocks — so it is built once per key and cached;
each SCP iteration only rewrites the numeric values (dynamics A_k/B_k/c_k, linearised rows, trust-region centre
and radius, targets, a terminal cost-to-go model in P and q: ``objective.py``) through precomputed index maps. No
modelling layer runs inside the loop. The dynamics rows x_{j+1} − A_j x_j − B_j u_j − ν_j = c_j stay in the state's
units (only columns are scaled): their multipliers y give λ_{j+1} = ∂(optimum)/∂c_j = −y_j (``costates``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp

from ttompc.scenarios.base import BlockKind
from ttompc.solvers.objective import ConicObjective, ConicValues
from ttompc.solvers.spec import SubproblemData, SubproblemSpec, structural_mask


@dataclass
class _Group:
    """Rows of one cone type with their COO entries; values either constant or gathered from update data."""

    n_rows: int = 0
    rows: list[np.ndarray] = field(default_factory=list)
    cols: list[np.ndarray] = field(default_factory=list)
    vals: list[tuple[str, Any]] = field(default_factory=list)  # ("const", array) or ("data", (key, index array, sign))
    b: list[tuple[np.ndarray, tuple[str, Any, float]]] = field(default_factory=list)  # (rows, (key, index, sign))

    def add_rows(self, count: int) -> np.ndarray:
        idx = np.arange(self.n_rows, self.n_rows + count)
        self.n_rows += count
        return idx


class AssembledSubproblem:
    """Sparse conic data of one structure plus the index maps that refresh its values from ``SubproblemData``."""

    def __init__(self, spec: SubproblemSpec) -> None:
        self.spec = spec
        H, n, m = spec.H, spec.n, spec.m
        self.n_var = 0
        self._scales: list[np.ndarray] = []
        sx, su = spec.units()
        self.ix = self._var((H + 1) * n, np.tile(sx, H + 1)).reshape(H + 1, n)
        self.iu = self._var(H * m, np.tile(su, H)).reshape(H, m)
        q_parts: list[tuple[np.ndarray, float]] = []  # (variables, linear cost weight)
        zero, nonneg = _Group(), _Group()
        self.soc_groups: list[_Group] = []
        # in this order: it fixes the variables' and rows' indices
        self._dynamics(zero, nonneg, q_parts)
        self._terminal(zero, nonneg, q_parts)
        self._stage_cost(nonneg, q_parts)
        for bi, sig in enumerate(spec.blocks):
            self._block(bi, sig, zero, nonneg, q_parts)
        self._trust_region(nonneg)
        self._finalise(zero, nonneg, q_parts)

    # ------------------------------------------------------------------------------------------------- sections
    def _dynamics(self, zero: _Group, nonneg: _Group, q_parts: list[tuple[np.ndarray, float]]) -> None:
        """x_0 = x_start and the dynamics rows (with the virtual control where the spec has one)."""
        spec, sx = self.spec, self.spec.units()[0]
        H, n, m = spec.H, spec.n, spec.m
        # x_0 = x_start
        r = zero.add_rows(n)
        self._entries(zero, r, self.ix[0], ("const", np.ones(n)))
        zero.b.append((r, ("x_start", np.arange(n), 1.0)))

        # dynamics: x_{j+1} − A_j x_j − B_j u_j − (ν⁺_j − ν⁻_j) = c_j
        rdyn = zero.add_rows(H * n).reshape(H, n)
        self.dyn_rows = rdyn  # the zero cone comes first: these are the assembled rows too
        self._entries(zero, rdyn, self.ix[1:], ("const", np.ones((H, n))))
        # A_j, B_j entries: only the structural nonzeros (spec.model_masks), gathered from the flattened arrays
        a_mask, b_mask = (None, None) if spec.model_masks is None else spec.model_masks
        for key, cols, width, mask in (("A", self.ix[:-1], n, a_mask), ("B", self.iu, m, b_mask)):
            keep = np.broadcast_to(structural_mask(mask, (n, width)), (H, n, width))
            rr = np.broadcast_to(rdyn[:, :, None], (H, n, width))[keep]
            cc = np.broadcast_to(cols[:, None, :], (H, n, width))[keep]
            self._entries(zero, rr, cc, ("data", (key, np.arange(H * n * width).reshape(H, n, width)[keep], -1.0)))
        zero.b.append((rdyn.ravel(), ("c", None, 1.0)))
        if spec.virtual_control:
            rows = spec.virtual_rows()
            k = H * len(rows)
            nu_p, nu_m = self._var(k, np.tile(sx[rows], H)), self._var(k, np.tile(sx[rows], H))
            self._entries(zero, rdyn[:, rows].ravel(), nu_p, ("const", -np.ones(k)))
            self._entries(zero, rdyn[:, rows].ravel(), nu_m, ("const", np.ones(k)))
            self._nonneg_vars(nonneg, np.concatenate([nu_p, nu_m]))
            q_parts.append((np.concatenate([nu_p, nu_m]), spec.penalty))

    def _terminal(self, zero: _Group, nonneg: _Group, q_parts: list[tuple[np.ndarray, float]]) -> None:
        """x_H = goal (penalised in that formulation), or the soft terminal term's cone."""
        spec = self.spec
        H, n = spec.H, spec.n
        # terminal condition
        if spec.end_form == "hard":
            r = zero.add_rows(n)
            self._entries(zero, r, self.ix[H], ("const", np.ones(n)))
            zero.b.append((r, ("goal", np.arange(n), 1.0)))
            if spec.penalized:
                sp_, sm_ = self._var(n), self._var(n)
                self._entries(zero, r, sp_, ("const", -np.ones(n)))
                self._entries(zero, r, sm_, ("const", np.ones(n)))
                self._nonneg_vars(nonneg, np.concatenate([sp_, sm_]))
                q_parts.append((np.concatenate([sp_, sm_]), spec.penalty))
        elif spec.end_form == "value":  # the cost-to-go model alone: x_H free, its block in P (``objective.py``)
            if not spec.terminal_value:
                raise ValueError("a spec with terminal 'value' needs terminal_value=True")
        else:  # τ ≥ ‖W (x_H − x̄)‖₂
            tau = self._var(1)
            g = self._soc(1 + n)
            self._entries(g, np.array([0]), tau, ("const", -np.ones(1)))
            self._entries(g, np.arange(1, n + 1), self.ix[H], ("data", ("terminal_weights", np.arange(n), -1.0)))
            g.b.append((np.arange(1, n + 1), ("weighted_target", np.arange(n), -1.0)))
            q_parts.append((tau, 1.0))

    def _stage_cost(self, nonneg: _Group, q_parts: list[tuple[np.ndarray, float]]) -> None:
        """The stage cost's epigraph (L1, L2); a quadratic one has none (it is in P)."""
        spec, su = self.spec, self.spec.units()[1]
        H, m = spec.H, spec.m
        # stage cost
        if spec.cost_norm == "l1":  # t ≥ |u| elementwise
            t = self._var(H * m, np.tile(su, H)).reshape(H, m)
            for sign in (1.0, -1.0):
                r = nonneg.add_rows(H * m).reshape(H, m)
                self._entries(nonneg, r, self.iu, ("const", np.full((H, m), sign)))
                self._entries(nonneg, r, t, ("const", -np.ones((H, m))))
            q_parts.append((t.ravel(), spec.fuel_weight))
        elif spec.cost_norm == "l2":  # t_j ≥ ‖u_j‖₂
            t = self._var(H, np.full(H, float(np.max(su))))
            for j in range(H):
                g = self._soc(1 + m)
                self._entries(g, np.array([0]), t[j : j + 1], ("const", -np.ones(1)))
                self._entries(g, np.arange(1, m + 1), self.iu[j], ("const", -np.ones(m)))
            q_parts.append((t, spec.fuel_weight))
        elif spec.cost_norm != "quad":
            raise ValueError(f"unknown cost norm {spec.cost_norm!r}")

    def _block(
        self, bi: int, sig: tuple, zero: _Group, nonneg: _Group, q_parts: list[tuple[np.ndarray, float]]
    ) -> None:
        """The rows of scenario constraint block ``bi`` (signature ``sig``), with their slacks where penalised."""
        spec, H = self.spec, self.spec.H
        _, kind, steps, M, has_u, soft, weight, two_sided = sig[:8]
        steps = np.asarray(steps, dtype=int)
        K = len(steps)
        if has_u and K and steps.max() >= H:
            raise ValueError(f"block {sig[0]!r} puts control rows on step {steps.max()} >= window length {H}")
        kind = BlockKind(kind)
        if kind is BlockKind.SOC:
            for kk in range(K):
                g = self._soc(M)
                rows = np.arange(M)
                self._block_entries(g, rows, bi, kk, steps[kk], has_u, sign=-1.0)
                g.b.append((rows, (f"h{bi}", kk * M + rows, -1.0)))
            return
        if kind is BlockKind.EQ and spec.soft_equalities:  # weight·τ, τ ≥ ‖G z − h‖₂ (MPC soft mode)
            tau = self._var(K)
            for kk in range(K):
                g = self._soc(1 + M)
                self._entries(g, np.array([0]), tau[kk : kk + 1], ("const", -np.ones(1)))
                rows = np.arange(1, M + 1)
                self._block_entries(g, rows, bi, kk, steps[kk], has_u, sign=-1.0)
                g.b.append((rows, (f"h{bi}", kk * M + np.arange(M), -1.0)))
            q_parts.append((tau, weight))
            return
        group = zero if kind is BlockKind.EQ else nonneg
        r = group.add_rows(K * M).reshape(K, M)
        for kk in range(K):
            self._block_entries(group, r[kk], bi, kk, steps[kk], has_u, sign=1.0)
        group.b.append((r.ravel(), (f"h{bi}", None, 1.0)))
        row_sets = [r]
        if two_sided:  # −(G z) ≤ −lower
            r_low = nonneg.add_rows(K * M).reshape(K, M)
            for kk in range(K):
                self._block_entries(nonneg, r_low[kk], bi, kk, steps[kk], has_u, sign=-1.0)
            nonneg.b.append((r_low.ravel(), (f"l{bi}", None, -1.0)))
            row_sets.append(r_low)
        if not spec.penalized:
            return
        if kind is BlockKind.INEQ and soft:  # one slack shared by both sides of a two-sided row
            s = self._var(K * M)
            for rows in row_sets:
                self._entries(nonneg, rows.ravel(), s, ("const", -np.ones(K * M)))
            self._nonneg_vars(nonneg, s)
            q_parts.append((s, spec.penalty))
        elif kind is BlockKind.EQ:
            sp_, sm_ = self._var(K * M), self._var(K * M)
            self._entries(group, r.ravel(), sp_, ("const", -np.ones(K * M)))
            self._entries(group, r.ravel(), sm_, ("const", np.ones(K * M)))
            self._nonneg_vars(nonneg, np.concatenate([sp_, sm_]))
            q_parts.append((np.concatenate([sp_, sm_]), spec.penalty))

    def _trust_region(self, nonneg: _Group) -> None:
        """The trust region about the reference on the spec's steps (2-norm cones or ∞-norm boxes)."""
        spec, n = self.spec, self.spec.n
        tr_states = np.asarray(spec.tr_states, dtype=int)
        if spec.trust == "l2":
            for j in tr_states:
                g = self._soc(1 + n)
                g.b.append((np.array([0]), ("delta", np.zeros(1, dtype=int), 1.0)))
                self._entries(g, np.arange(1, n + 1), self.ix[j], ("const", -np.ones(n)))
                g.b.append((np.arange(1, n + 1), ("X_ref", j * n + np.arange(n), -1.0)))
        elif spec.trust == "linf":
            for sign in (1.0, -1.0):
                r = nonneg.add_rows(len(tr_states) * n)
                self._entries(nonneg, r, self.ix[tr_states].ravel(), ("const", np.full(len(r), sign)))
                idx = (tr_states[:, None] * n + np.arange(n)).ravel()
                nonneg.b.append((r, ("delta", np.zeros(len(r), dtype=int), 1.0)))
                nonneg.b.append((r, ("X_ref", idx, sign)))
        elif spec.trust != "none":
            raise ValueError(f"unknown trust-region norm {spec.trust!r}")

    # ------------------------------------------------------------------------------------------------- building
    def _var(self, count: int, scale: np.ndarray | None = None) -> np.ndarray:
        idx = np.arange(self.n_var, self.n_var + count)
        self.n_var += count
        self._scales.append(np.ones(count) if scale is None else np.asarray(scale, dtype=np.float64))
        return idx

    def _soc(self, dim: int) -> _Group:
        g = _Group()
        g.add_rows(dim)
        self.soc_groups.append(g)
        return g

    def _nonneg_vars(self, group: _Group, idx: np.ndarray) -> None:
        r = group.add_rows(len(idx))
        self._entries(group, r, idx, ("const", -np.ones(len(idx))))

    @staticmethod
    def _entries(group: _Group, rows: np.ndarray, cols: np.ndarray, vals: tuple[str, Any]) -> None:
        rows, cols = np.broadcast_arrays(np.asarray(rows), np.asarray(cols))
        group.rows.append(rows.ravel())
        group.cols.append(cols.ravel())
        group.vals.append(vals)

    def _block_entries(
        self, group: _Group, rows: np.ndarray, bi: int, kk: int, step: int, has_u: bool, sign: float
    ) -> None:
        """Gx[kk] (M, n) on x_step and Gu[kk] (M, m) on u_step, gathered from the flattened (K, M, ·) arrays; only
        the block's structural nonzeros (its masks in the signature)."""
        n, m = self.spec.n, self.spec.m
        M = len(rows)
        sig = self.spec.blocks[bi]
        parts = [(f"G{bi}x", self.ix[step], n, sig[8] if len(sig) > 8 else None)]
        if has_u:
            parts.append((f"G{bi}u", self.iu[step], m, sig[9] if len(sig) > 9 else None))
        for key, cols, width, mask in parts:
            keep = structural_mask(mask, (M, width))
            rr = np.broadcast_to(rows[:, None], (M, width))[keep]
            cc = np.broadcast_to(cols[None, :], (M, width))[keep]
            self._entries(
                group, rr, cc, ("data", (key, (kk * M * width + np.arange(M * width)).reshape(M, width)[keep], sign))
            )

    def _finalise(self, zero: _Group, nonneg: _Group, q_parts: list[tuple[np.ndarray, float]]) -> None:
        groups = [zero, nonneg, *self.soc_groups]
        offsets = np.cumsum([0] + [g.n_rows for g in groups])
        self.n_con = int(offsets[-1])
        rows, cols, self._val_src, self._b_src = [], [], [], []
        nnz = 0
        for g, off in zip(groups, offsets[:-1], strict=True):
            for r, c, v in zip(g.rows, g.cols, g.vals, strict=True):
                rows.append(r + off)
                cols.append(c)
                self._val_src.append((slice(nnz, nnz + len(r)), v))
                nnz += len(r)
            for r, payload in g.b:
                self._b_src.append((r + off, payload))
        rows_a, cols_a = np.concatenate(rows), np.concatenate(cols)
        self.nnz = nnz
        # CSC order: sort by (col, row); keep explicit zeros so the pattern never changes between iterations
        self._perm = np.lexsort((rows_a, cols_a))
        self._indices = rows_a[self._perm].astype(np.int64)
        self._indptr = np.concatenate([[0], np.cumsum(np.bincount(cols_a, minlength=self.n_var))]).astype(np.int64)
        if len(np.unique(cols_a * self.n_con + rows_a)) != nnz:
            raise AssertionError("duplicate entries in the assembled constraint matrix")
        self.cones = [("zero", zero.n_rows), ("nonneg", nonneg.n_rows)] + [("soc", g.n_rows) for g in self.soc_groups]
        # the solver sees z = S z̃ with S the characteristic magnitudes: columns of A, q and P are scaled once
        self.scale = np.concatenate(self._scales)
        self._entry_scale = self.scale[cols_a[self._perm]]
        q = np.zeros(self.n_var)
        for idx, w in q_parts:
            q[idx] += w
        self.objective = ConicObjective(self.spec, self.scale, q * self.scale, self.ix[-1], self.iu)
        self._coo_vals = np.zeros(nnz)
        for slc, (kind, payload) in self._val_src:
            if kind == "const":
                self._coo_vals[slc] = np.ravel(payload)

    # ------------------------------------------------------------------------------------------------- updating
    def update(self, data: SubproblemData) -> ConicValues:
        """One iteration's numbers: the column-scaled A (in CSC data order), b, P's upper triangle and q."""
        src = self._sources(data)
        vals = self._coo_vals
        for slc, (kind, payload) in self._val_src:
            if kind == "data":
                key, idx, sign = payload
                flat = src[key]
                vals[slc] = sign * (flat if idx is None else flat[idx])
        b = np.zeros(self.n_con)
        for rows, (key, idx, sign) in self._b_src:
            flat = src[key]
            b[rows] += sign * (flat if idx is None else flat[idx])
        P, q, offset = self.objective.values(data.terminal_cost)
        return ConicValues(vals[self._perm] * self._entry_scale, b, P, q, offset)

    def matrix(self, values: np.ndarray) -> sp.csc_matrix:
        return sp.csc_matrix((values, self._indices, self._indptr), shape=(self.n_con, self.n_var))

    def row_blocks(self, k: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, int]]:
        """The CSC patterns of rows [0, k) and [k, n_con) of ``matrix``, each as (positions in ``values``, row
        indices, column pointers, rows): built once per structure, so a backend that takes the two blocks apart
        (QOCO: equalities and cones) gathers their values instead of converting and slicing a matrix per solve."""
        cols = np.repeat(np.arange(self.n_var), np.diff(self._indptr))
        out = []
        for top in (True, False):
            take = np.flatnonzero(self._indices < k if top else self._indices >= k)
            ptr = np.concatenate([[0], np.cumsum(np.bincount(cols[take], minlength=self.n_var))]).astype(np.int64)
            out.append((take, self._indices[take] - (0 if top else k), ptr, k if top else self.n_con - k))
        return out

    def _sources(self, data: SubproblemData) -> dict[str, np.ndarray]:
        src: dict[str, np.ndarray] = {
            "x_start": data.x_start,
            "A": np.ascontiguousarray(data.model.A).ravel(),
            "B": np.ascontiguousarray(data.model.B).ravel(),
            "c": np.ascontiguousarray(data.model.c).ravel(),
            "goal": data.goal,
            "X_ref": np.ascontiguousarray(data.X_ref).ravel(),
            "delta": np.array([data.delta]),
        }
        if data.terminal_weights is not None and data.terminal_target is not None:
            src["terminal_weights"] = data.terminal_weights
            src["weighted_target"] = data.terminal_weights * data.terminal_target
        for bi, block in enumerate(data.blocks):
            src[f"G{bi}x"] = np.ascontiguousarray(block.Gx).ravel()
            if block.Gu is not None:
                src[f"G{bi}u"] = np.ascontiguousarray(block.Gu).ravel()
            src[f"h{bi}"] = np.ascontiguousarray(block.h).ravel()
            if block.lower is not None:
                src[f"l{bi}"] = np.ascontiguousarray(block.lower).ravel()
        return src

    def costates(self, y: np.ndarray) -> np.ndarray:
        """λ (H, n) for x_1..x_H, per unit of the state, from a solver's multipliers ``y`` (n_con,) of A z + s = b
        (the dynamics rows are in the zero cone, first): −y on the dynamics rows (module doc)."""
        return -np.asarray(y)[self.dyn_rows]

    def split(self, z_scaled: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """States and controls from the solver's (scaled) solution vector."""
        z = z_scaled * self.scale
        return z[self.ix], z[self.iu]
