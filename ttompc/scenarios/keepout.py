"""Linearised keep-out zones shared by all scenarios: balls and axis-aligned ellipsoids ‖E(p − c)‖ ≥ r."""

from __future__ import annotations

import numpy as np

from ttompc.scenarios.base import BlockKind, ConstraintBlock


def keepout_distance(
    P: np.ndarray, centres: np.ndarray, radius: float | np.ndarray, scale: np.ndarray | None = None
) -> np.ndarray:
    """Signed clearance ‖E(p − c)‖ − r of positions (T, d) to each zone: (T, n_zones) (negative = inside)."""
    E = np.ones(P.shape[-1]) if scale is None else np.asarray(scale, dtype=np.float64)
    radius = np.broadcast_to(np.asarray(radius, dtype=np.float64), (len(centres),))
    return np.linalg.norm((P[:, None, :] - centres[None]) * E, axis=-1) - radius[None]


def keepout_block(
    P_ref: np.ndarray,
    centres: np.ndarray,
    radius: float | np.ndarray,
    steps: np.ndarray,
    n: int,
    scale: np.ndarray | None = None,
) -> ConstraintBlock:
    """Tangent half-spaces n̂ᵀ(p − c) ≥ r of keep-out balls at the radial projection of the reference p̄ (fact
    sheet §5.1); position = the first ``d`` state entries. Conservative: the half-space excludes the whole ball.
    With ``scale`` (ellipsoid E = diag(1/semi-axes)) the same construction is done in scaled coordinates."""
    K, d = P_ref.shape
    n_obs = len(centres)
    E = np.ones(d) if scale is None else np.asarray(scale, dtype=np.float64)
    radius = np.broadcast_to(np.asarray(radius, dtype=np.float64), (n_obs,))
    diff = (P_ref[:, None, :] - centres[None]) * E  # (K, n_obs, d) in scaled coordinates
    norm = np.linalg.norm(diff, axis=-1, keepdims=True)
    fallback = np.zeros(d)
    fallback[0] = 1.0
    normal = np.where(norm > 1e-9, diff / np.maximum(norm, 1e-12), fallback)  # unit normal, scaled space
    # n̂ᵀE(p − c) ≥ r  <=>  −(E n̂)ᵀ p ≤ −r − (E n̂)ᵀ c
    row = normal * E
    Gx = np.zeros((K, n_obs, n))
    Gx[:, :, :d] = -row
    h = -radius[None, :] - np.einsum("kod,od->ko", row, centres)
    mask = np.zeros((n_obs, n), bool)
    mask[:, :d] = True  # only the position enters
    return ConstraintBlock(
        "obstacles", BlockKind.INEQ, steps, Gx, None, h, nonconvex=True, obstacle=True, soft=True, Gx_mask=mask
    )
