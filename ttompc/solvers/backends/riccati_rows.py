"""The Riccati kernel's constraint families (``riccati_kernel``): rows g_iᵀy = Σ_v coef[i, v]·y[k_of[i], cols[i, v]] ≤
d_i (+ e_i if ρ_i > 0), the arrays of a ``riccati_qp.Rows`` (the kernel's boxes are rows of width 1: one code path
for both). The functions take the arrays, not the structure: numba counts references to arrays taken out of a
structure, which would cost more than the work of a small family.

Each constraint has a slack s = d − gᵀy + e ≥ 0 with multiplier λ, and (soft) e ≥ 0 with multiplier μ = ρ − λ.
Eliminating s, e, λ, μ from the Newton system leaves per constraint a weight w = 1/(s/λ + e/μ) on gᵀΔy: each
stage's Hessian gains Σ w g gᵀ. The per-constraint state lives in the rows of one (14, m) array ``z``, named below;
each function is one pass over a family.
"""

from __future__ import annotations

from ttompc.solvers.backends.riccati_jit import jit

# slack s, multiplier λ, penalty slack e and its multiplier μ (soft only), residuals of the slack definition (rs) and
# of e's stationarity (re), 1/λ, 1/μ, the Newton weight w, ξ, and the step (Δs, Δλ, Δe, Δμ)
S, LAM, E, MU, RS, RE, IL, IM, W, XI, DS, DL, DE, DM = range(14)
STATE_ROWS = 14  # rows of ``z``


@jit
def start(y, k_of, cols, coef, d, rho, z):
    """A strictly interior start: s, e ≥ 0.1 with s − e = d − gᵀy for soft rows (primal residual 0), λ = μ = ρ/2, and
    s ≥ 0.1, λ = 1 for hard rows. Returns the number of complementarity pairs. (Why 0.1: measured in docs/design.md.)"""
    count = 0
    for i in range(d.shape[0]):
        a = 0.0
        for v in range(cols.shape[1]):
            a += coef[i, v] * y[k_of[i], cols[i, v]]
        room = d[i] - a
        if rho[i] > 0:
            z[S, i] = max(room, 0.0) + 0.1
            z[E, i] = z[S, i] - room
            z[LAM, i] = 0.5 * rho[i]
            z[MU, i] = 0.5 * rho[i]
            count += 2
        else:
            z[S, i] = max(room, 0.1)
            z[LAM, i] = 1.0
            count += 1
    return count


@jit
def residuals(y, ry, k_of, cols, coef, d, rho, z):
    """Add g·λ to the stationarity residual, set rs = s − d + gᵀy − e and re = ρ − λ − μ; return the
    complementarity Σ sλ + eμ and the largest |rs|, |re| (NaN if any is not finite)."""
    gap = res = probe = 0.0
    for i in range(d.shape[0]):
        k, lam = k_of[i], z[LAM, i]
        a = 0.0
        for v in range(cols.shape[1]):
            a += coef[i, v] * y[k, cols[i, v]]
            ry[k, cols[i, v]] += coef[i, v] * lam
        rs = z[S, i] - d[i] + a - z[E, i]
        re = rho[i] - lam - z[MU, i] if rho[i] > 0 else 0.0
        z[RS, i], z[RE, i] = rs, re
        gap += z[S, i] * lam + z[E, i] * z[MU, i]
        res = max(res, abs(rs), abs(re))
        probe += rs + re
    return gap, res + 0.0 * probe  # non-finite if any residual is


@jit
def weights(Qt, k_of, cols, coef, rho, z):
    """w = 1/(s/λ + e/μ) and Qt += w g gᵀ."""
    for i in range(rho.shape[0]):
        il = 1.0 / z[LAM, i]
        im = 1.0 / z[MU, i] if rho[i] > 0 else 0.0
        w = 1.0 / (z[S, i] * il + z[E, i] * im)
        z[IL, i], z[IM, i], z[W, i] = il, im, w
        k = k_of[i]
        for a in range(cols.shape[1]):
            ga = w * coef[i, a]
            for b in range(cols.shape[1]):
                Qt[k, cols[i, a], cols[i, b]] += ga * coef[i, b]


@jit
def rhs(corrector, sigma_mu, rt, k_of, cols, coef, z):
    """The complementarity right-hand sides (kept in the Δλ, Δμ rows until ``steps``), ξ with Δλ = w (gᵀΔy + ξ),
    and rt += g w ξ. The corrector adds Mehrotra's second-order term and centring."""
    for i in range(z.shape[1]):
        rl = z[S, i] * z[LAM, i]
        rm = z[E, i] * z[MU, i]
        if corrector:
            rl += z[DS, i] * z[DL, i] - sigma_mu
            rm += z[DE, i] * z[DM, i] - sigma_mu
        xi = z[RS, i] - rl * z[IL, i] + (rm + z[E, i] * z[RE, i]) * z[IM, i]
        z[XI, i], z[DL, i], z[DM, i] = xi, rl, rm
        g = z[W, i] * xi
        for v in range(cols.shape[1]):
            rt[k_of[i], cols[i, v]] += coef[i, v] * g


@jit
def steps(amax, dy, k_of, cols, coef, rho, z):
    """Recover (Δs, Δλ, Δe, Δμ) of every constraint from gᵀΔy; return the largest step ≤ amax that keeps s, λ, e, μ
    ≥ 0."""
    for i in range(z.shape[1]):
        g = 0.0
        for v in range(cols.shape[1]):
            g += coef[i, v] * dy[k_of[i], cols[i, v]]
        s, lam, e, mu = z[S, i], z[LAM, i], z[E, i], z[MU, i]
        dl = z[W, i] * (g + z[XI, i])
        ds = (-z[DL, i] - s * dl) * z[IL, i]
        if amax * ds < -s:
            amax = -s / ds
        if amax * dl < -lam:
            amax = -lam / dl
        dm = de = 0.0
        if rho[i] > 0:
            dm = z[RE, i] - dl
            de = (-z[DM, i] - e * dm) * z[IM, i]
            if amax * de < -e:
                amax = -e / de
            if amax * dm < -mu:
                amax = -mu / dm
        z[DL, i], z[DS, i], z[DM, i], z[DE, i] = dl, ds, dm, de
    return amax


@jit
def step_gap(alpha, z):
    """Σ sλ + eμ after a step α."""
    total = 0.0
    for i in range(z.shape[1]):
        total += (z[S, i] + alpha * z[DS, i]) * (z[LAM, i] + alpha * z[DL, i])
        total += (z[E, i] + alpha * z[DE, i]) * (z[MU, i] + alpha * z[DM, i])
    return total


@jit
def update(alpha, z):
    """Take the step α."""
    for i in range(z.shape[1]):
        z[S, i] += alpha * z[DS, i]
        z[LAM, i] += alpha * z[DL, i]
        z[E, i] += alpha * z[DE, i]
        z[MU, i] += alpha * z[DM, i]
