"""The cost of a sampled terminal set (LMPC; ``TerminalCost.samples``) at a state x:

    h(x) = min over λ ∈ Δ of ‖W(x − Zᵀλ)‖₂ + cᵀλ,   Δ = {λ ∈ ℝᴷ : λ ≥ 0, 1ᵀλ = 1},

with Z (K, n) the samples, c (K,) their costs-to-go and W = diag(w): the terminal part of a window's convex
subproblem (``subproblem_terminal``) at a fixed end state, i.e. what the SCP merit must read.

Computed exactly, without an iterative solver: the minimum of a convex function over the simplex is attained in the
relative interior of some face, and on a face whose edge vectors are independent the minimiser over the face's
affine hull has a closed form (``_face_minimiser``). A face whose edge vectors are dependent (e.g. a repeated sample)
attains its minimum on its boundary, so skipping it loses nothing. The faces are enumerated: 2ᴷ − 1 of them, meant
for the handful of samples a window carries.
"""

from __future__ import annotations

import itertools

import numpy as np

RANK_TOL = 1e-10  # a face whose edge vectors' smallest singular value is below this fraction of the largest: dependent
INTERIOR_TOL = 1e-9  # how far outside its face a face's minimiser may lie and still count (rounding)


def hull_cost(x: np.ndarray, weights: np.ndarray, samples: np.ndarray, costs: np.ndarray) -> float:
    """h(x) (module doc) for the state ``x`` (n,), the weights ``weights`` (n,), the samples (K, n) and their costs
    (K,)."""
    a = np.asarray(weights, np.float64) * np.asarray(x, np.float64)
    B = (np.asarray(weights, np.float64) * np.asarray(samples, np.float64)).T  # (n, K): the weighted samples
    c = np.asarray(costs, np.float64)
    K = B.shape[1]

    def value(lam: np.ndarray) -> float:
        return float(np.linalg.norm(a - B @ lam) + c @ lam)

    best = min(value(e) for e in np.eye(K))
    for size in range(2, K + 1):
        for face in itertools.combinations(range(K), size):
            lam = _face_minimiser(a, B, c, np.asarray(face))
            if lam is not None:
                best = min(best, value(lam))
    return best


def _face_minimiser(a: np.ndarray, B: np.ndarray, c: np.ndarray, face: np.ndarray) -> np.ndarray | None:
    """The minimiser λ (K,) of ‖a − Bλ‖ + cᵀλ over the affine hull of the simplex face ``face`` (sample indices),
    where it exists and lies in the face; else None.

    With λ = e₀ + Σⱼ μⱼ(eⱼ − e₀) over the face's samples 0, 1, …, p the function is ‖r − Dμ‖ + dᵀμ + c₀
    (r = a − B₀, D = [Bⱼ − B₀], d = [cⱼ − c₀]). For D = QR of full column rank write v = Q Qᵀ r − Dμ ∈ range(D),
    ρ = ‖r − Q Qᵀ r‖ and g = Q R⁻ᵀ d: the function is √(ρ² + ‖v‖²) − gᵀv + const, which is bounded below with a
    minimiser iff ‖g‖ < 1, at v = ρ g / √(1 − ‖g‖²)."""
    base, rest = face[0], face[1:]
    D = B[:, rest] - B[:, [base]]
    sv = np.linalg.svd(D, compute_uv=False)
    if sv[0] == 0.0 or sv[-1] <= RANK_TOL * sv[0]:
        return None
    Q, R = np.linalg.qr(D)
    r = a - B[:, base]
    h = np.linalg.solve(R.T, c[rest] - c[base])  # g = Q h, ‖g‖ = ‖h‖
    gamma = float(np.linalg.norm(h))
    if gamma >= 1.0:
        return None
    Qr = Q.T @ r
    rho = float(np.linalg.norm(r - Q @ Qr))
    mu = np.linalg.solve(R, Qr - rho * h / np.sqrt(1.0 - gamma * gamma))  # R μ = Qᵀ(r − v)
    lam = np.zeros(B.shape[1])
    lam[rest], lam[base] = mu, 1.0 - mu.sum()
    if lam.min() < -INTERIOR_TOL:
        return None
    lam = np.clip(lam, 0.0, None)
    return lam / lam.sum()
