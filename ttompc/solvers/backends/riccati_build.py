"""The compiled path of the Riccati backend's per-iteration Python (``riccati.StageQP``): the scenario blocks' boxes and
rows of the stage QP (``constraints``, the per-block loop of ``StageQP.build``) and the subproblem's objective
(``objective``, ``StageQPData.objective``), each one numba call per block or per solve instead of dozens of small
NumPy operations. The NumPy forms stay the reference: ``RiccatiSolver.compiled = False`` runs them, and
tests/test_riccati_build.py checks that both give the same stage QPs (same entries, same order), the same iterates
and the same statuses on every scenario.

The same arithmetic in the same order as the reference, no fastmath: a box's bound is its right-hand side over
|coefficient|, a row's coefficients are divided by their 2-norm, whose squares are summed in order
as NumPy sums them over the reference's (R, width) array, so the stage QPs are equal to the
bit on any instruction set. Compiled once per machine into numba's disk cache, keyed on this file alone (it calls no
compiled code from other files).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ttompc.compiled import Kernel
from ttompc.solvers.backends.riccati_qp import Boxes, Rows, StageQPData
from ttompc.solvers.spec import SubproblemData

KERNEL = Kernel("the riccati backend's stage-QP build", [Path(__file__)], error_model="numpy")
_LOADED: set[str] = set()  # "build" once its first call in this process has compiled it or loaded it from the cache


def constraints(stage: Any, data: SubproblemData, d_fixed: np.ndarray) -> tuple[Boxes, Rows]:
    """The boxes and rows of ``stage`` (a ``riccati.StageQP``, which imports this module) for one iteration's
    ``data``: the fixed boxes with right-hand sides ``d_fixed`` (those not finite dropped), then each scenario block's
    boxes and rows (``_block``), as ``StageQP._constraints`` orders them."""
    if not _LOADED:
        from ttompc.progress import status

        status("riccati backend: loading its stage-QP build (compiled once per machine, ~15 s)")
        _LOADED.add("build")
    n, m = stage.spec.n, stage.spec.m
    cap = sum(2 * b.live.size for b in stage.blocks)
    bk, bj = np.empty(len(d_fixed) + cap, np.int64), np.empty(len(d_fixed) + cap, np.int64)
    bs, bd, brho = (np.empty(len(d_fixed) + cap) for _ in range(3))
    rk, ri, rg = np.empty(cap, np.int64), np.empty((cap, stage.width), np.int64), np.empty((cap, stage.width))
    rd, rrho = np.empty(cap), np.empty(cap)
    nb = _fixed(stage._box_k, stage._box_j, stage._box_s, d_fixed, stage._box_rho, bk, bj, bs, bd, brho)
    nr = 0
    no_u = np.zeros((0, 0, m))
    for b, block in zip(stage.blocks, data.blocks, strict=True):
        h = np.ascontiguousarray(block.h, np.float64)
        lower = h if b.is_eq or block.lower is None else np.ascontiguousarray(block.lower, np.float64)
        Gu = no_u if block.Gu is None else np.ascontiguousarray(block.Gu, np.float64)
        nb, nr = _block(
            np.ascontiguousarray(block.Gx, np.float64),
            Gu,
            block.Gu is not None,
            h,
            lower,
            b.steps,
            b.live,
            b.single,
            b.cols,
            b.valid,
            b.two_sided,
            b.rho,
            stage.sx,
            stage.su,
            n,
            bk,
            bj,
            bs,
            bd,
            brho,
            nb,
            rk,
            ri,
            rg,
            rd,
            rrho,
            nr,
        )
    return Boxes(bk[:nb], bj[:nb], bs[:nb], bd[:nb], brho[:nb]), Rows(rk[:nr], ri[:nr], rg[:nr], rd[:nr], rrho[:nr])


def objective(qp: StageQPData, y: np.ndarray) -> float:
    """``qp.objective(y)`` (``StageQPData.objective``) in one compiled pass (sums in another order: equal to
    rounding)."""
    c, b, r = qp.cost, qp.boxes, qp.rows
    return float(_objective(c.Qd, c.q, c.QN, y, b.k, b.j, b.sign, b.d, b.rho, r.k, r.cols, r.coef, r.d, r.rho))


@KERNEL.jit
def _fixed(k, j, s, d, rho, bk, bj, bs, bd, brho):  # pragma: no cover - compiled
    """The fixed boxes with a finite right-hand side into the output's first places; returns their count."""
    nb = 0
    for i in range(d.shape[0]):
        if np.isfinite(d[i]):
            bk[nb], bj[nb], bs[nb], bd[nb], brho[nb] = k[i], j[i], s[i], d[i], rho[i]
            nb += 1
    return nb


@KERNEL.jit
def _block(  # pragma: no cover - compiled
    Gx,
    Gu,
    has_u,
    upper,
    lower,
    steps,
    live,
    single,
    cols,
    valid,
    two_sided,
    rho,
    sx,
    su,
    n,
    bk,
    bj,
    bs,
    bd,
    brho,
    nb,
    rk,
    ri,
    rg,
    rd,
    rrho,
    nr,
):
    """One scenario block's constraints appended at nb (boxes) and nr (rows); returns the new counts. Rows on one
    variable (``single``) are boxes sign(g)·y ≤ upper/|g| (and −sign(g)·y ≤ −lower/|g| where two-sided) at penalty
    ρ|g|, g the scaled coefficient (none where g = 0); the others rows g/‖g‖ · y ≤ upper/‖g‖ (and the negated row
    where two-sided) at penalty ρ‖g‖ (‖g‖ = 0 read as 1). Live (K, M) rows only, row-major, the upper sides of a kind
    before its lower sides; those whose bound is not finite are dropped."""
    K, M = live.shape
    width = cols.shape[1]
    g = np.empty(width)
    for side in range(2 if two_sided else 1):
        sign = 1.0 if side == 0 else -1.0
        for kk in range(K):
            for r in range(M):
                if not (live[kk, r] and single[r]):
                    continue
                v = _scaled(Gx, Gu, has_u, sx, su, n, kk, r, cols[r, 0])
                if v == 0.0:
                    continue
                a = abs(v)
                bound = upper[kk, r] / a if side == 0 else -lower[kk, r] / a
                if np.isfinite(bound):
                    bk[nb], bj[nb], bs[nb], bd[nb], brho[nb] = steps[kk], cols[r, 0], sign * np.sign(v), bound, rho * a
                    nb += 1
    for side in range(2 if two_sided else 1):
        for kk in range(K):
            for r in range(M):
                if not live[kk, r] or single[r]:
                    continue
                for w in range(width):
                    g[w] = _scaled(Gx, Gu, has_u, sx, su, n, kk, r, cols[r, w]) * (1.0 if valid[r, w] else 0.0)
                sq = 0.0  # summed in order, as NumPy's norm over the rows of the reference's (R, width) array
                for w in range(width):
                    sq += g[w] * g[w]
                norm = np.sqrt(sq)
                if norm == 0.0:
                    norm = 1.0
                bound = upper[kk, r] / norm if side == 0 else -lower[kk, r] / norm
                if np.isfinite(bound):
                    rk[nr], rd[nr], rrho[nr] = steps[kk], bound, rho * norm
                    for w in range(width):
                        ri[nr, w] = cols[r, w]
                        rg[nr, w] = g[w] / norm if side == 0 else -(g[w] / norm)
                    nr += 1
    return nb, nr


def _scaled(Gx, Gu, has_u, sx, su, n, kk, r, col):  # pragma: no cover - compiled
    """The scaled coefficient of column ``col`` (of [x, u]) in row r of step kk: Gx·sx or Gu·su (0 without Gu).
    Inlined into ``_block`` (a call would count references to its arrays each time: 2-3× the loop's cost), so a
    leaf with one way out (``riccati_jit.jit_inlined``)."""
    v = 0.0
    if col < n:
        v = Gx[kk, r, col] * sx[col]
    elif has_u:
        v = Gu[kk, r, col - n] * su[col - n]
    return v


_scaled = KERNEL.jit(_scaled, forceinline=True)


@KERNEL.jit
def _objective(Qd, q, QN, y, bk, bj, bs, bd, brho, rk, ri, rg, rd, rrho):  # pragma: no cover - compiled
    """Σ ½ Qd y² + q y, ½ x_Nᵀ QN x_N and the penalties ρ·max(gᵀy − d, 0) of the boxes and rows."""
    value = 0.0
    for k in range(y.shape[0]):
        for j in range(y.shape[1]):
            value += 0.5 * Qd[k, j] * y[k, j] ** 2 + q[k, j] * y[k, j]
    N, nq = y.shape[0] - 1, QN.shape[0]
    quad = 0.0
    for a in range(nq):
        t = 0.0
        for b in range(nq):
            t += QN[a, b] * y[N, b]
        quad += y[N, a] * t
    value += 0.5 * quad
    for i in range(bd.shape[0]):
        value += brho[i] * max(bs[i] * y[bk[i], bj[i]] - bd[i], 0.0)
    for i in range(rd.shape[0]):
        t = 0.0
        for w in range(ri.shape[1]):
            t += rg[i, w] * y[rk[i], ri[i, w]]
        value += rrho[i] * max(t - rd[i], 0.0)
    return value
