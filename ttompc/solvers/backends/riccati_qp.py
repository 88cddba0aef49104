"""The Riccati kernel's interface (``riccati_kernel.solve``): a stage-wise QP, the solver's options and its result
as named structures, which the kernel takes as they are (numba types ``NamedTuple`` arguments).

The problem (stage k = 0..N, y_k = [x_k (NX), u_k (NU)]; stage N's u part is a dummy with unit cost):

    min  Σ_k ½ Σ_j Qd[k, j] y[k, j]² + q[k]ᵀ y_k  +  ½ x_Nᵀ QN x_N  +  Σ_i ρ_i e_i
    s.t. x_{k+1} = A_k x_k + B_k u_k + c_k,   x_0 fixed,
         box i:  sign_i y[k_i, j_i] ≤ d_i + e_i,     row i:  Σ_w coef[i, w] y[k_i, cols[i, w]] ≤ d_i + e_i,
         e_i ≥ 0 for soft constraints (ρ_i > 0); e_i = 0 for hard ones (ρ_i = 0);
         optionally one second-order cone τ ≥ ‖w∘(x_N − center)‖₂ on τ = y[N, NX], stage N's first dummy control
         (the caller prices τ through q and gives it no Qd): an MPC window's soft terminal term.

QN, a dense symmetric positive semidefinite block on x_N, carries a terminal cost-to-go model with q[N] its linear
term; an empty (0, 0) QN is none.

Every array is C-contiguous, float64 or (indices) int64: the kernel's compiled entry point, which ``solve`` calls
without numba's type dispatch after the first call per (NX, NU), is specialised to these types and does not check
them (another dtype raises; an array that is not C-contiguous is read as if it were).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Dynamics(NamedTuple):
    """x_{k+1} = A_k x_k + B_k u_k + c_k for k < N, x_0 = x0."""

    A: np.ndarray  # (N, NX, NX)
    B: np.ndarray  # (N, NX, NU)
    c: np.ndarray  # (N, NX)
    x0: np.ndarray  # (NX,)


class StageCost(NamedTuple):
    """Σ_k ½ Σ_j Qd[k, j] y[k, j]² + q[k]ᵀ y_k + ½ x_Nᵀ QN x_N."""

    Qd: np.ndarray  # (N + 1, NX + NU) diagonal stage Hessians, ≥ 0 (stage N's dummy controls: 1, τ's: 0)
    q: np.ndarray  # (N + 1, NX + NU)
    QN: np.ndarray = np.zeros((0, 0))  # (NX, NX) symmetric PSD, added to stage N's state Hessian; (0, 0): none


class Boxes(NamedTuple):
    """sign_i · y[k_i, j_i] ≤ d_i (+ e_i ≥ 0 at cost ρ_i e_i where ρ_i > 0; hard where ρ_i = 0)."""

    k: np.ndarray  # (nb,) int64 stages
    j: np.ndarray  # (nb,) int64 columns of y_k
    sign: np.ndarray  # (nb,) ±1
    d: np.ndarray  # (nb,)
    rho: np.ndarray  # (nb,) ≥ 0

    @classmethod
    def none(cls) -> Boxes:
        """No boxes."""
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0))


class Rows(NamedTuple):
    """Σ_w coef[i, w] · y[k_i, cols[i, w]] ≤ d_i (+ e_i as for ``Boxes``); a row narrower than ``width`` is padded
    with zero coefficients."""

    k: np.ndarray  # (nr,) int64 stages
    cols: np.ndarray  # (nr, width) int64 columns of y_k
    coef: np.ndarray  # (nr, width)
    d: np.ndarray  # (nr,)
    rho: np.ndarray  # (nr,) ≥ 0

    @classmethod
    def none(cls, width: int = 1) -> Rows:
        """No rows."""
        return cls(
            np.zeros(0, np.int64), np.zeros((0, width), np.int64), np.zeros((0, width)), np.zeros(0), np.zeros(0)
        )


class TerminalCone(NamedTuple):
    """τ ≥ ‖w∘(x_N − center)‖₂ with τ = y[N, NX]; both empty: no cone."""

    w: np.ndarray  # (NX,) or (0,)
    center: np.ndarray  # (NX,) or (0,)

    @classmethod
    def none(cls) -> TerminalCone:
        """No cone."""
        return cls(np.zeros(0), np.zeros(0))


class StageQPData(NamedTuple):
    """One stage-wise QP (the module docstring's problem)."""

    dynamics: Dynamics
    cost: StageCost
    boxes: Boxes = Boxes.none()
    rows: Rows = Rows.none()
    cone: TerminalCone = TerminalCone.none()

    @property
    def shape(self) -> tuple[int, int, int]:
        """(N, NX, NU)."""
        N, nx, nu = self.dynamics.B.shape
        return N, nx, nu

    def objective(self, y: np.ndarray) -> float:
        """The objective at y (N + 1, NX + NU), penalties included, τ at its price in q (not the cone's norm)."""
        cost, b, r = self.cost, self.boxes, self.rows
        value = float(np.sum(0.5 * cost.Qd * y**2 + cost.q * y))
        if cost.QN.size:
            x = y[-1, : cost.QN.shape[0]]
            value += 0.5 * float(x @ cost.QN @ x)
        value += float(b.rho @ np.maximum(b.sign * y[b.k, b.j] - b.d, 0.0))
        value += float(r.rho @ np.maximum(np.sum(r.coef * y[r.k[:, None], r.cols], axis=1) - r.d, 0.0))
        return value


class RiccatiOptions(NamedTuple):
    """When the interior-point iterations stop, and where they start."""

    tol: float  # largest residual (stationarity, dynamics, slack definitions, the cone's)
    gap_tol: float  # total complementarity
    max_iter: int
    # 0: a cold start of the constraints' slacks and multipliers (``riccati_rows.start``); δ > 0: from the ones the
    # caller's ``DualState`` holds, centred by δ (``riccati_rows.warm_start``), cold after all where that start's
    # residual is too large (``riccati_kernel.WARM_RESIDUAL``); the terminal cone's always cold
    warm: float = 0.0


STATE_COLS = 16  # columns of a ``DualState`` array (``riccati_rows``: a constraint's state is two cache lines)


class DualState(NamedTuple):
    """The constraints' interior-point state (``riccati_rows``' columns: slack s, multiplier λ, penalty slack e, its
    multiplier μ, scratch), a row a constraint in the order of the QP's boxes and rows: a solve leaves its last
    iterate's here, and one with ``RiccatiOptions.warm`` > 0 starts from it (the same constraints, in the same
    order: the caller's to ensure)."""

    boxes: np.ndarray  # (nb, STATE_COLS)
    rows: np.ndarray  # (nr, STATE_COLS)

    @classmethod
    def empty(cls, qp: StageQPData) -> DualState:
        """A state for ``qp``'s constraints (zeros: for a cold start)."""
        return cls(np.zeros((qp.boxes.d.shape[0], STATE_COLS)), np.zeros((qp.rows.d.shape[0], STATE_COLS)))


class RiccatiResult(NamedTuple):
    """How a solve ended; the solution itself is written into the caller's y and π."""

    status: int  # 0 converged, 1 iteration limit, 2 numerical breakdown, 3 the best iterate within 100× both tolerances
    iterations: int
    residual: float  # largest residual of the returned iterate
    gap: float  # its total complementarity
