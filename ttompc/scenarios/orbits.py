"""Relative orbital motion for the RPOD scenario (paper §V-A): quasi-nonsingular relative orbital elements
(ROE) scaled by the chief semi-major axis, their map to the chief's RTN frame, the J2 secular state transition matrix
of Koenig, Guffanti & D'Amico (JGCD 2017) and the Gauss-variational control input matrix.

Orbital elements are ``oe = [a, e, i, Ω, ω, M]`` (m, -, rad, rad, rad, rad); every function is vectorised over the
leading axes of ``oe`` so that a whole horizon of matrices is built in one call. ROE are
``a·[δa, δλ, δe_x, δe_y, δi_x, δi_y]`` in metres; Δv and RTN velocities in m/s.
"""

from __future__ import annotations

import numpy as np

J2 = 0.001082635819197
R_EARTH = 6.3781363e6  # m
MU_EARTH = 3.986004415e14  # m³/s²

# ISS chief orbit at t_0 = 0 (the authors' research code's).
ISS_OE = np.array(
    [
        R_EARTH + 416e3,
        0.0005581,
        np.deg2rad(51.6418),
        np.deg2rad(301.0371),
        np.deg2rad(26.1813),
        np.deg2rad(68.2333),
    ]
)


def mean_motion(a: np.ndarray | float) -> np.ndarray:
    return np.sqrt(MU_EARTH / np.asarray(a, dtype=np.float64) ** 3)


def orbital_period(a: np.ndarray | float) -> np.ndarray:
    return 2.0 * np.pi / mean_motion(a)


def propagate_chief(oe0: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Keplerian chief propagation (only M advances, by n·t; the J2 drift of Ω, ω is ignored as in the reference):
    elements (len(t), 6) at times ``t`` (s)."""
    oe0 = np.asarray(oe0, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    oe = np.broadcast_to(oe0, (*t.shape, 6)).copy()
    oe[..., 5] = oe0[5] + mean_motion(oe0[0]) * t
    return oe


def roe_to_rtn_matrix(oe: np.ndarray) -> np.ndarray:
    """Ψ(oe) (..., 6, 6): near-circular linear map from scaled ROE to RTN position/velocity (u = ω + M)."""
    oe = np.asarray(oe, dtype=np.float64)
    n = mean_motion(oe[..., 0])
    u = oe[..., 4] + oe[..., 5]
    c, s = np.cos(u), np.sin(u)
    z = np.zeros_like(u)
    o = np.ones_like(u)
    rows = [
        [o, z, -c, -s, z, z],
        [z, o, 2 * s, -2 * c, z, z],
        [z, z, z, z, s, -c],
        [z, z, n * s, -n * c, z, z],
        [-1.5 * n, z, 2 * n * c, 2 * n * s, z, z],
        [z, z, z, z, n * c, n * s],
    ]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def control_matrix(oe: np.ndarray) -> np.ndarray:
    """B(oe) (..., 6, 3) in seconds: the Gauss variational equations for an RTN impulse Δv (near-circular chief)."""
    oe = np.asarray(oe, dtype=np.float64)
    n = mean_motion(oe[..., 0])
    u = oe[..., 4] + oe[..., 5]
    c, s = np.cos(u) / n, np.sin(u) / n
    z = np.zeros_like(u)
    rows = [
        [z, 2 / n, z],
        [-2 / n, z, z],
        [s, 2 * c, z],
        [-c, 2 * s, z],
        [z, z, c],
        [z, z, s],
    ]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def stm_j2(oe: np.ndarray, tau: float | np.ndarray, j2: float = J2) -> np.ndarray:
    """Φ(oe, τ) (..., 6, 6): J2 secular STM of the quasi-nonsingular ROE (Koenig, Guffanti & D'Amico 2017).

    The entries are Koenig et al.'s (0-based indices here), as in the authors' research code. With ``j2=0`` it
    reduces to Keplerian drift (only the δλ ← δa entry −1.5·n·τ), which the tests compare against integrated
    two-body motion.
    """
    oe = np.asarray(oe, dtype=np.float64)
    a, e, inc, omega = oe[..., 0], oe[..., 1], oe[..., 2], oe[..., 4]
    tau = np.broadcast_to(np.asarray(tau, dtype=np.float64), a.shape)
    n = mean_motion(a)
    eta = np.sqrt(1.0 - e**2)
    kappa = 0.75 * j2 * R_EARTH**2 * np.sqrt(MU_EARTH) / (a**3.5 * eta**4)
    E, F, G = 1.0 + eta, 4.0 + 3.0 * eta, 1.0 / eta**2
    cos_i, sin_i = np.cos(inc), np.sin(inc)
    P, Q = 3.0 * cos_i**2 - 1.0, 5.0 * cos_i**2 - 1.0
    S, T = np.sin(2.0 * inc), sin_i**2
    omega_dot = kappa * Q
    omega_f = omega + omega_dot * tau
    exi, eyi = e * np.cos(omega), e * np.sin(omega)
    exf, eyf = e * np.cos(omega_f), e * np.sin(omega_f)
    cw, sw = np.cos(omega_dot * tau), np.sin(omega_dot * tau)
    kt = kappa * tau

    phi = np.zeros((*a.shape, 6, 6))
    phi[..., 0, 0] = phi[..., 1, 1] = phi[..., 4, 4] = phi[..., 5, 5] = 1.0
    phi[..., 1, 0] = -(3.5 * kappa * E * P + 1.5 * n) * tau
    phi[..., 1, 2] = kt * exi * F * G * P
    phi[..., 1, 3] = kt * eyi * F * G * P
    phi[..., 1, 4] = -kt * F * S
    phi[..., 2, 0] = 3.5 * kt * eyf * Q
    phi[..., 2, 2] = cw - 4.0 * kt * exi * eyf * G * Q
    phi[..., 2, 3] = -sw - 4.0 * kt * eyi * eyf * G * Q
    phi[..., 2, 4] = 5.0 * kt * eyf * S
    phi[..., 3, 0] = -3.5 * kt * exf * Q
    phi[..., 3, 2] = sw + 4.0 * kt * exi * exf * G * Q
    phi[..., 3, 3] = cw + 4.0 * kt * eyi * exf * G * Q
    phi[..., 3, 4] = -5.0 * kt * exf * S
    phi[..., 5, 0] = 3.5 * kt * S
    phi[..., 5, 2] = -4.0 * kt * exi * G * S
    phi[..., 5, 3] = -4.0 * kt * eyi * G * S
    phi[..., 5, 4] = 2.0 * kt * T
    return phi
