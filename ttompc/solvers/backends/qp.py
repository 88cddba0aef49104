"""The SCP subproblem as a compact QP, for subproblems without cones (L1 or quadratic cost, hard terminal state,
∞-norm trust region), solved by PIQP with in-place data updates:

    min ½ zᵀPz + cᵀz   s.t.   A z = b,   h_l ≤ G z ≤ h_u,   z_l ≤ z ≤ z_u

It poses the same optimisation problem as the conic assembly (``subproblem.py``) with fewer rows, because a QP
solver takes two-sided rows and variable bounds directly:

* L1 cost: u = u⁺ − u⁻ with u± ≥ 0 as bounds and cost Σ(u⁺ + u⁻) (the conic form needs t and 2·H·m rows);
* a soft row lower ≤ g ≤ h with exact penalty ρ·dist(g, [lower, h]) is the single row lower ≤ g − e⁺ + e⁻ ≤ h,
  e± ≥ 0 (the conic form needs two rows and a slack row); a one-sided row needs e⁺ only; penalised equalities
  and virtual control as g − e⁺ + e⁻ = h;
* the ∞-norm trust region is a pair of bounds on each state, not 2n rows per step, and hard rows that touch one
  variable each (the free-flyer's table, the quadrotor's control box; from the blocks' structural masks) are
  bounds intersected with it.

Every number that changes between SCP iterations is gathered in one pass from a flat vector of the iteration's
data (dynamics, constraint blocks, trust-region centre and radius) through index maps built once per structure,
so an update is a handful of numpy gathers and the solver keeps its symbolic factorisation.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from ttompc.scenarios.base import BlockKind
from ttompc.solvers.backends.base import BackendSolution, Fallback, SubproblemSolver, cone_error, is_qp
from ttompc.solvers.spec import SubproblemData, SubproblemSpec, structural_mask

# a sparse-pattern entry: (rows, cols, source index into the flat data vector, coefficient[, keep mask])
_Entry = tuple[np.ndarray | float, ...]


@dataclass
class _Vector:
    """A right-hand side or bound vector: constant base plus data gathered into given positions."""

    base: np.ndarray
    dest: list[np.ndarray]
    src: list[np.ndarray]
    coef: list[np.ndarray]

    def freeze(self) -> None:
        cat = (lambda xs, dt: np.concatenate(xs).astype(dt)) if self.dest else (lambda xs, dt: np.zeros(0, dt))
        self._dest, self._src, self._coef = cat(self.dest, np.int64), cat(self.src, np.int64), cat(self.coef, float)

    def values(self, flat: np.ndarray) -> np.ndarray:
        out = self.base.copy()
        if len(self._dest):
            out += np.bincount(self._dest, weights=self._coef * flat[self._src], minlength=len(out))
        return out


class QPSubproblem:
    """Index maps from ``SubproblemData`` to the compact QP of one structure (see the module docstring)."""

    def __init__(self, spec: SubproblemSpec) -> None:
        if not is_qp(spec):
            raise ValueError(cone_error("piqp"))
        self.spec = spec
        H, n, m = spec.H, spec.n, spec.m
        self._layout(spec)
        sx, su = spec.units()
        self._scale: list[np.ndarray] = []
        self._lo: list[np.ndarray] = []  # constant lower bounds per variable group
        self._cost: list[np.ndarray] = []
        self._boxes: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self.n_var = 0
        self.ix = self._var(np.tile(sx, H + 1), -np.inf, 0.0).reshape(H + 1, n)
        if spec.cost_norm == "l1":  # u = u⁺ − u⁻, cost Σ(u⁺ + u⁻)
            up = self._var(np.tile(su, H), 0.0, spec.fuel_weight).reshape(H, m)
            um = self._var(np.tile(su, H), 0.0, spec.fuel_weight).reshape(H, m)
            self.u_parts = [(up, 1.0), (um, -1.0)]
        else:
            self.u_parts = [(self._var(np.tile(su, H), -np.inf, 0.0).reshape(H, m), 1.0)]
        # entries: (row, col, source index into the flat data vector, coefficient)
        eq: list[_Entry] = []
        ineq: list[_Entry] = []
        self.n_eq = self.n_in = 0
        b_parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        lo_parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        hi_parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        lo_inf: list[np.ndarray] = []  # inequality rows without a lower side
        one = self._const_index(1.0)

        # x_0 = x_start
        r = self._rows("eq", n)
        eq.append((r, self.ix[0], np.full(n, one), np.ones(n)))
        b_parts.append((r, self._key("x_start"), np.ones(n)))

        # dynamics x_{j+1} − A_j x_j − B_j u_j − ν⁺ + ν⁻ = c_j
        a_mask, b_mask = (None, None) if spec.model_masks is None else spec.model_masks
        rd = self._rows("eq", H * n).reshape(H, n)
        eq.append((rd, self.ix[1:], np.full((H, n), one), np.ones((H, n))))
        rr = np.broadcast_to(rd[:, :, None], (H, n, n))
        cols = np.broadcast_to(self.ix[:-1][:, None, :], (H, n, n))
        eq.append((rr, cols, self._key("A").reshape(H, n, n), -1.0, structural_mask(a_mask, (n, n))))
        for iu, sign in self.u_parts:
            rr = np.broadcast_to(rd[:, :, None], (H, n, m))
            cols = np.broadcast_to(iu[:, None, :], (H, n, m))
            eq.append((rr, cols, self._key("B").reshape(H, n, m), -sign, structural_mask(b_mask, (n, m))))
        b_parts.append((rd.ravel(), self._key("c"), np.ones(H * n)))
        if spec.virtual_control:
            rows = spec.virtual_rows()
            self._penalised_slacks(eq, rd[:, rows].ravel(), np.tile(sx[rows], H), one)

        # terminal x_H = goal (penalised: x_H − e⁺ + e⁻ = goal)
        r = self._rows("eq", n)
        eq.append((r, self.ix[H], np.full(n, one), np.ones(n)))
        b_parts.append((r, self._key("goal"), np.ones(n)))
        if spec.penalized:
            self._penalised_slacks(eq, r, sx, one)

        # scenario blocks
        for bi, sig in enumerate(spec.blocks):
            name, kind, steps, M, has_u, soft, _, two_sided, gx_mask, gu_mask = sig
            kind = BlockKind(kind)
            steps = np.asarray(steps, dtype=np.int64)
            K = len(steps)
            if has_u and K and steps.max() >= H:
                raise ValueError(f"block {name!r} puts control rows on step {steps.max()} >= window length {H}")
            is_eq = kind is BlockKind.EQ
            hard = not (spec.penalized and soft)
            if kind is BlockKind.INEQ and hard and self._bound_rows(bi, steps, M, has_u, two_sided, gx_mask, gu_mask):
                continue
            r = self._rows("eq" if is_eq else "in", K * M).reshape(K, M)
            dest = eq if is_eq else ineq
            rr = np.broadcast_to(r[:, :, None], (K, M, n))
            cols = np.broadcast_to(self.ix[steps][:, None, :], (K, M, n))
            dest.append((rr, cols, self._key(f"G{bi}x").reshape(K, M, n), 1.0, structural_mask(gx_mask, (M, n))))
            if has_u:
                for iu, sign in self.u_parts:
                    rr = np.broadcast_to(r[:, :, None], (K, M, m))
                    cols = np.broadcast_to(iu[steps][:, None, :], (K, M, m))
                    dest.append(
                        (rr, cols, self._key(f"G{bi}u").reshape(K, M, m), sign, structural_mask(gu_mask, (M, m)))
                    )
            if is_eq:
                b_parts.append((r.ravel(), self._key(f"h{bi}"), np.ones(K * M)))
            else:
                hi_parts.append((r.ravel(), self._key(f"h{bi}"), np.ones(K * M)))
                if two_sided:
                    lo_parts.append((r.ravel(), self._key(f"l{bi}"), np.ones(K * M)))
                else:
                    lo_inf.append(r.ravel())
            if spec.penalized and (is_eq or soft):  # a one-sided row only ever needs e⁺
                signs = (-1.0, 1.0) if is_eq or two_sided else (-1.0,)
                self._penalised_slacks(dest, r.ravel(), np.ones(K * M), one, signs)

        self._finalise(eq, ineq, b_parts, lo_parts, hi_parts, lo_inf)

    # ------------------------------------------------------------------------------------------------- building
    def _bound_rows(self, bi: int, steps: np.ndarray, M: int, has_u: bool, two_sided: bool, gx_mask, gu_mask) -> bool:
        """A hard block whose every row touches one variable (a box on states, or on controls unless they are split
        for the L1 cost) becomes bounds on those variables, intersected with the trust region each iteration. False
        if it is not such a block."""
        n, m, K = self.spec.n, self.spec.m, len(steps)
        if gx_mask is None or (has_u and gu_mask is None):
            return False
        mask = np.hstack(
            [structural_mask(gx_mask, (M, n)), structural_mask(gu_mask, (M, m)) if has_u else np.zeros((M, m), bool)]
        )
        col = np.argmax(mask, axis=1)  # (M,) the one variable of each row: state entries, then controls
        on_u = col >= n
        if not np.all(mask.sum(axis=1) == 1) or (on_u.any() and len(self.u_parts) != 1):
            return False
        rows = np.arange(M)
        gx = self._key(f"G{bi}x").reshape(K, M, n)[:, rows, np.minimum(col, n - 1)]
        cols = self.ix[steps][:, np.minimum(col, n - 1)]
        if on_u.any():
            gu = self._key(f"G{bi}u").reshape(K, M, m)[:, rows, np.maximum(col - n, 0)]
            gx = np.where(on_u, gu, gx)
            cols = np.where(on_u, self.u_parts[0][0][steps][:, np.maximum(col - n, 0)], cols)
        lower = self._key(f"l{bi}") if two_sided else np.full(K * M, self._const_index(-np.inf))
        self._boxes.append((cols.ravel(), gx.ravel(), self._key(f"h{bi}"), lower))
        return True

    def bounds(self, flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Variable bounds of one iteration: constants, the ∞-norm trust region and the box rows."""
        z_l, z_u = self.z_l.values(flat), self.z_u.values(flat)
        if self._box is not None:  # lower ≤ g·x ≤ h row by row, the tightest bound per variable
            cols, g_idx, h_idx, l_idx, starts, ucols = self._box
            g = flat[g_idx]
            with np.errstate(divide="ignore", invalid="ignore"):
                a, b = flat[h_idx] / g, flat[l_idx] / g
            inv = 1.0 / self.scale[cols]
            upper = np.where(g > 0, a, np.where(g < 0, b, np.inf)) * inv
            lower = np.where(g > 0, b, np.where(g < 0, a, -np.inf)) * inv
            z_u[ucols] = np.minimum(z_u[ucols], np.minimum.reduceat(upper, starts))
            z_l[ucols] = np.maximum(z_l[ucols], np.maximum.reduceat(lower, starts))
        return z_l, z_u

    def _layout(self, spec: SubproblemSpec) -> None:
        """Offsets of every data array in the flat per-iteration vector (shapes follow from the spec)."""
        H, n, m = spec.H, spec.n, spec.m
        sizes = {"A": H * n * n, "B": H * n * m, "c": H * n, "x_start": n, "goal": n, "X_ref": (H + 1) * n, "delta": 1}
        for bi, sig in enumerate(spec.blocks):
            K, M, has_u, two_sided = len(sig[2]), sig[3], sig[4], sig[7]
            sizes[f"G{bi}x"] = K * M * n
            if has_u:
                sizes[f"G{bi}u"] = K * M * m
            sizes[f"h{bi}"] = K * M
            if two_sided:
                sizes[f"l{bi}"] = K * M
        self._offsets, off = {}, 0
        for key, size in sizes.items():
            self._offsets[key] = (off, size)
            off += size
        self._n_data = off
        self._consts: list[float] = []

    def _key(self, key: str) -> np.ndarray:
        off, size = self._offsets[key]
        return np.arange(off, off + size)

    def _const_index(self, value: float) -> int:
        self._consts.append(value)
        return self._n_data + len(self._consts) - 1

    def _var(self, scale: np.ndarray, lower: float, cost: float) -> np.ndarray:
        idx = np.arange(self.n_var, self.n_var + len(scale))
        self.n_var += len(scale)
        self._scale.append(np.asarray(scale, dtype=np.float64))
        self._lo.append(np.full(len(scale), lower))
        self._cost.append(np.full(len(scale), cost))
        return idx

    def _rows(self, which: str, count: int) -> np.ndarray:
        if which == "eq":
            r = np.arange(self.n_eq, self.n_eq + count)
            self.n_eq += count
        else:
            r = np.arange(self.n_in, self.n_in + count)
            self.n_in += count
        return r

    def _penalised_slacks(
        self, dest: list, rows: np.ndarray, scale: np.ndarray, one: int, signs: tuple[float, ...] = (-1.0, 1.0)
    ) -> None:
        """Row − e⁺ + e⁻, e± ≥ 0 with cost ρ·(e⁺ + e⁻): an exact L1 penalty on the row's violation."""
        k = len(rows)
        for sign in signs:
            e = self._var(scale, 0.0, self.spec.penalty)
            dest.append((rows, e, np.full(k, one), np.full(k, sign)))

    def _finalise(self, eq, ineq, b_parts, lo_parts, hi_parts, lo_inf) -> None:
        self.scale = np.concatenate(self._scale)
        self._const = np.asarray(self._consts, dtype=np.float64)
        self.A_map = _CSCMap(eq, self.n_eq, self.n_var, self.scale)
        self.G_map = _CSCMap(ineq, self.n_in, self.n_var, self.scale)
        self.c = np.concatenate(self._cost) * self.scale
        P = np.zeros(self.n_var)
        if self.spec.cost_norm == "quad":
            for iu, _ in self.u_parts:
                P[iu.ravel()] = self.spec.fuel_weight
        self.P = sp.diags(P * self.scale**2, format="csc")
        self.b = _vector(np.zeros(self.n_eq), b_parts)
        h_l = np.zeros(self.n_in)
        for r in lo_inf:
            h_l[r] = -np.inf
        self.h_l = _vector(h_l, lo_parts)
        self.h_u = _vector(np.zeros(self.n_in), hi_parts)
        # bounds (scaled variables): constant ones, plus the ∞-norm trust region X_ref ± δ on the listed states
        z_l, z_u = np.concatenate(self._lo), np.full(self.n_var, np.inf)
        lo_tr, hi_tr = [], []
        if self.spec.trust == "linf" and self.spec.tr_states:
            j = np.asarray(self.spec.tr_states, dtype=np.int64)
            cols = self.ix[j].ravel()
            z_l[cols], z_u[cols] = 0.0, 0.0
            ref = self._key("X_ref").reshape(-1, self.spec.n)[j].ravel()
            delta = np.full(len(cols), self._offsets["delta"][0])
            inv = 1.0 / self.scale[cols]
            lo_tr = [(cols, ref, inv), (cols, delta, -inv)]
            hi_tr = [(cols, ref, inv), (cols, delta, inv)]
        self.z_l, self.z_u = _vector(z_l, lo_tr), _vector(z_u, hi_tr)
        self._box = None
        if self._boxes:  # entries sorted by variable, for one reduction per variable
            cols, g_idx, h_idx, l_idx = (np.concatenate(a) for a in zip(*self._boxes, strict=True))
            order = np.argsort(cols, kind="stable")
            cols = cols[order]
            ucols, starts = np.unique(cols, return_index=True)
            self._box = (cols, g_idx[order], h_idx[order], l_idx[order], starts, ucols)

    # ------------------------------------------------------------------------------------------------- updating
    def flat(self, data: SubproblemData) -> np.ndarray:
        """The iteration's data in the layout of ``_layout`` followed by the constants."""
        parts: list[np.ndarray | list[float]] = [
            np.ravel(data.model.A),
            np.ravel(data.model.B),
            np.ravel(data.model.c),
            data.x_start,
            data.goal,
            np.ravel(data.X_ref),
            [data.delta],
        ]
        for block in data.blocks:
            parts.append(np.ravel(block.Gx))
            if block.Gu is not None:
                parts.append(np.ravel(block.Gu))
            parts.append(np.ravel(block.h))
            if block.lower is not None:
                parts.append(np.ravel(block.lower))
        parts.append(self._const)
        flat = np.concatenate(parts)
        if len(flat) != self._n_data + len(self._const):
            raise ValueError("subproblem data do not match the structure they were assembled for")
        return flat

    def split(self, z_scaled: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        z = z_scaled * self.scale
        U = sum(sign * z[iu] for iu, sign in self.u_parts)
        return z[self.ix], U


class _CSCMap:
    """A sparse matrix whose CSC values are ``coef * flat[src]``: the pattern (explicit zeros kept) is fixed."""

    def __init__(self, entries: list[_Entry], n_rows: int, n_cols: int, col_scale: np.ndarray) -> None:
        rows: list[np.ndarray] = []
        cols: list[np.ndarray] = []
        src: list[np.ndarray] = []
        coef: list[np.ndarray] = []
        for r, c, s, k, *keep in entries:
            arrays = np.broadcast_arrays(np.asarray(r), np.asarray(c), np.asarray(s), np.asarray(k, dtype=float))
            sel = np.broadcast_to(keep[0], arrays[0].shape) if keep else np.ones(arrays[0].shape, bool)
            for out, a in zip((rows, cols, src, coef), arrays, strict=True):
                out.append(a[sel])
        rows_a = np.concatenate(rows) if rows else np.zeros(0, np.int64)
        cols_a = np.concatenate(cols) if cols else np.zeros(0, np.int64)
        if len(np.unique(cols_a * max(n_rows, 1) + rows_a)) != len(rows_a):
            raise AssertionError("duplicate entries in the assembled QP matrix")
        perm = np.lexsort((rows_a, cols_a))
        self.shape = (n_rows, n_cols)
        self.indices = rows_a[perm].astype(np.int32)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(cols_a, minlength=n_cols))]).astype(np.int32)
        self.src = (np.concatenate(src) if src else np.zeros(0, np.int64))[perm].astype(np.int64)
        self.coef = (np.concatenate(coef) if coef else np.zeros(0))[perm] * col_scale[cols_a[perm]]

    def values(self, flat: np.ndarray) -> np.ndarray:
        return self.coef * flat[self.src]

    def matrix(self, values: np.ndarray) -> sp.csc_matrix:
        return sp.csc_matrix((values, self.indices, self.indptr), shape=self.shape)


def _vector(base: np.ndarray, parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> _Vector:
    vec = _Vector(base, [np.asarray(p[0]) for p in parts], [np.asarray(p[1]) for p in parts], [])
    vec.coef = [np.broadcast_to(np.asarray(p[2], dtype=float), np.shape(p[0])) for p in parts]
    vec.freeze()
    return vec


class PIQPSolver:
    """The compact QP solved by PIQP (sparse LDLᵀ): set up once per structure, then ``update`` in place. On a
    numerical failure the same subproblem goes to ``fallback`` (a conic solver), if given."""

    name = "piqp"

    def __init__(self, spec: SubproblemSpec, fallback: Callable[[], SubproblemSolver] | None = None) -> None:
        import piqp

        self._piqp = piqp
        self.qp = QPSubproblem(spec)
        self.solver: Any = None  # piqp.SparseSolver, set up on the first solve
        self.fallback = Fallback(fallback)
        self._rescale = False  # the next update recomputes the equilibration (set by ``restart``)

    def restart(self) -> None:
        """The next solve equilibrates its own data instead of reusing the first data's scaling, which would make
        its optimum depend (at solver tolerance) on whatever this cached solver solved before."""
        self._rescale = True
        self.fallback.restart()

    def solve(self, data: SubproblemData) -> tuple[np.ndarray | None, np.ndarray | None, BackendSolution]:
        t0 = time.perf_counter()
        qp = self.qp
        flat = qp.flat(data)
        A, G = qp.A_map.values(flat), qp.G_map.values(flat)
        b, h_l, h_u = qp.b.values(flat), qp.h_l.values(flat), qp.h_u.values(flat)
        z_l, z_u = qp.bounds(flat)
        if self.solver is None:
            self._A, self._G = qp.A_map.matrix(A), qp.G_map.matrix(G)
            self.solver = self._piqp.SparseSolver()
            self.solver.settings.verbose = False
            # keep the equilibration of the first data: later iterations differ little (same optima in less time,
            # measured in docs/design.md)
            self.solver.settings.preconditioner_reuse_on_update = True
            self.solver.setup(qp.P, qp.c, self._A, b, self._G, h_l, h_u, z_l, z_u)
        else:  # same pattern: overwrite the values of the persistent matrices
            self._A.data[:] = A
            self._G.data[:] = G
            self.solver.settings.preconditioner_reuse_on_update = not self._rescale
            self.solver.update(A=self._A, b=b, G=self._G, h_l=h_l, h_u=h_u, x_l=z_l, x_u=z_u)
            self.solver.settings.preconditioner_reuse_on_update = True
        self._rescale = False
        status = str(self.solver.solve())
        elapsed = time.perf_counter() - t0
        ok = "PIQP_SOLVED" in status
        res = self.solver.result
        sol = BackendSolution(
            np.asarray(res.x) if ok else None,
            float(res.info.primal_obj),
            ok,
            "PRIMAL_INFEASIBLE" in status,
            status,
            elapsed,
        )
        if ok:
            assert sol.z is not None  # PIQP returns its iterate whenever it reports SOLVED
            X, U = qp.split(sol.z)
            return X, U, sol
        return self.fallback.take(data, sol)
