"""The Riccati kernel's constraint families (``riccati_kernel``): rows g_iᵀy = Σ_v coef[i, v]·y[k_of[i], cols[i, v]] ≤
d_i (+ e_i if ρ_i > 0), the arrays of a ``riccati_qp.Rows``, and boxes sign_i·y[k_of[i], j_of[i]] ≤ d_i (+ e_i), a
``riccati_qp.Boxes``: rows of width 1 with coefficient ±1, whose passes (``box_*``) do the rows' arithmetic without
the loop over a row's width (the same results to the bit: a product by ±1 is exact). The functions take the arrays,
not the structure: numba counts references to arrays taken out of a structure, which would cost more than the work
of a small family.

Each constraint has a slack s = d − gᵀy + e ≥ 0 with multiplier λ, and (soft) e ≥ 0 with multiplier μ = ρ − λ.
Eliminating s, e, λ, μ from the Newton system leaves per constraint a weight w = 1/(s/λ + e/μ) on gᵀΔy: each stage's
Hessian gains Σ w g gᵀ. The per-constraint state lives in one (m, 16) array ``z``, a constraint's in one row (two cache
lines; its columns named below): the passes are scalar loops (gathers, scatters and ratio tests), which read one row per
constraint faster than 14 rows of a (14, m) layout (measured in docs/benchmarks.md). An iteration makes four passes over
a family: ``residuals`` (taking the previous iteration's step first), ``weights`` (with the predictor's right-hand
side), ``rhs`` (the corrector's) and ``steps`` (twice; they also sum the terms of the complementarity after a step,
which Mehrotra's centring needs).
"""

from __future__ import annotations

import numpy as np

from ttompc.solvers.backends.riccati_jit import jit, jit_inlined

# slack s, multiplier λ, penalty slack e and its multiplier μ (soft only), residuals of the slack definition (rs) and
# of e's stationarity (re), 1/λ, 1/μ, the Newton weight w, ξ, and the step (Δs, Δλ, Δe, Δμ)
S, LAM, E, MU, RS, RE, IL, IM, W, XI, DS, DL, DE, DM = range(14)  # of ``riccati_qp.STATE_COLS`` (16)


@jit
def start(y, k_of, cols, coef, d, rho, z):
    """A strictly interior start: s, e ≥ 0.1 with s − e = d − gᵀy for soft rows (primal residual 0), λ = μ = ρ/2, and
    s ≥ 0.1, λ = 1 for hard rows; the step (Δs, Δλ, Δe, Δμ) 0. Returns the number of complementarity pairs. (Why
    0.1: measured in docs/design.md.)"""
    count = 0
    for i in range(d.shape[0]):
        a = 0.0
        for v in range(cols.shape[1]):
            a += coef[i, v] * y[k_of[i], cols[i, v]]
        room = d[i] - a
        if rho[i] > 0:
            z[i, S] = max(room, 0.0) + 0.1
            z[i, E] = z[i, S] - room
            z[i, LAM] = 0.5 * rho[i]
            z[i, MU] = 0.5 * rho[i]
            count += 2
        else:
            z[i, S] = max(room, 0.1)
            z[i, LAM] = 1.0
            z[i, E] = z[i, MU] = 0.0
            count += 1
        z[i, DS] = z[i, DL] = z[i, DE] = z[i, DM] = 0.0
    return count


@jit
def warm_start(y, k_of, cols, coef, d, rho, delta, z):
    """``start`` from the s, λ, e, μ in ``z`` (a previous solve's): the slacks re-evaluated at y (s = d − gᵀy + e,
    primal residual 0), then each pair (s, λ), (e, μ) centred to a product ≥ δ by raising its smaller member (to
    ≥ √δ if both are below it); hard rows keep e = μ = 0. The step 0; returns the number of complementarity pairs."""
    count = 0
    for i in range(d.shape[0]):
        a = 0.0
        for v in range(cols.shape[1]):
            a += coef[i, v] * y[k_of[i], cols[i, v]]
        if rho[i] > 0:
            z[i, E], z[i, MU] = _centred(z[i, E], z[i, MU], delta)
            count += 2
        else:
            z[i, E] = z[i, MU] = 0.0
            count += 1
        z[i, S], z[i, LAM] = _centred(d[i] - a + z[i, E], z[i, LAM], delta)
        z[i, DS] = z[i, DL] = z[i, DE] = z[i, DM] = 0.0
    return count


@jit_inlined
def _centred(a, b, delta):
    """(a, b) with a·b ≥ δ: the larger raised to ≥ √δ, then the smaller to ≥ δ / the larger (a and b ≥ 0 first)."""
    a, b = max(a, 0.0), max(b, 0.0)
    if a >= b:
        a = max(a, np.sqrt(delta))
        b = max(b, delta / a)
    else:
        b = max(b, np.sqrt(delta))
        a = max(a, delta / b)
    return a, b


@jit
def residuals(alpha, y, ry, k_of, cols, coef, d, rho, z):
    """Take the step α of the previous iteration (0 on the first: ``start`` zeroes it) in s, λ, e, μ; then add g·λ to
    the stationarity residual, set rs = s − d + gᵀy − e and re = ρ − λ − μ; return the complementarity Σ sλ + eμ and
    the largest |rs|, |re| (NaN if any is not finite)."""
    gap = res = probe = 0.0
    for i in range(d.shape[0]):
        s, lam, e, mu = _take_step(alpha, z, i)
        k = k_of[i]
        a = 0.0
        for v in range(cols.shape[1]):
            a += coef[i, v] * y[k, cols[i, v]]
            ry[k, cols[i, v]] += coef[i, v] * lam
        rs = s - d[i] + a - e
        re = rho[i] - lam - mu if rho[i] > 0 else 0.0
        z[i, RS], z[i, RE] = rs, re
        gap += s * lam + e * mu
        res = max(res, abs(rs), abs(re))
        probe += rs + re
    return gap, res + 0.0 * probe  # non-finite if any residual is


@jit
def box_residuals(alpha, y, ry, k_of, j_of, sign, d, rho, z):
    """``residuals`` of boxes."""
    gap = res = probe = 0.0
    for i in range(d.shape[0]):
        s, lam, e, mu = _take_step(alpha, z, i)
        k, j, g = k_of[i], j_of[i], sign[i]
        ry[k, j] += g * lam
        rs = s - d[i] + g * y[k, j] - e
        re = rho[i] - lam - mu if rho[i] > 0 else 0.0
        z[i, RS], z[i, RE] = rs, re
        gap += s * lam + e * mu
        res = max(res, abs(rs), abs(re))
        probe += rs + re
    return gap, res + 0.0 * probe


@jit
def weights(Qt, rt, k_of, cols, coef, rho, z):
    """w = 1/(s/λ + e/μ), Qt += w g gᵀ, and the predictor's right-hand side: the complementarities sλ, eμ (kept in
    the Δλ, Δμ rows until ``steps``), ξ with Δλ = w (gᵀΔy + ξ), and rt += g w ξ."""
    for i in range(rho.shape[0]):
        w, xi = _weight(rho[i] > 0, z, i)
        k = k_of[i]
        for a in range(cols.shape[1]):
            ga = w * coef[i, a]
            for b in range(cols.shape[1]):
                Qt[k, cols[i, a], cols[i, b]] += ga * coef[i, b]
        g = w * xi
        for v in range(cols.shape[1]):
            rt[k, cols[i, v]] += coef[i, v] * g


@jit
def box_weights(Qt, rt, k_of, j_of, sign, rho, z):
    """``weights`` of boxes."""
    for i in range(rho.shape[0]):
        w, xi = _weight(rho[i] > 0, z, i)
        k, j, g = k_of[i], j_of[i], sign[i]
        Qt[k, j, j] += w * g * g
        rt[k, j] += g * (w * xi)


@jit
def rhs(sigma_mu, rt, k_of, cols, coef, z):
    """The corrector's right-hand side: ``weights``' with Mehrotra's second-order term and centring σμ."""
    for i in range(z.shape[0]):
        g = z[i, W] * _corrector_xi(sigma_mu, z, i)
        for v in range(cols.shape[1]):
            rt[k_of[i], cols[i, v]] += coef[i, v] * g


@jit
def box_rhs(sigma_mu, rt, k_of, j_of, sign, z):
    """``rhs`` of boxes."""
    for i in range(z.shape[0]):
        rt[k_of[i], j_of[i]] += sign[i] * (z[i, W] * _corrector_xi(sigma_mu, z, i))


@jit
def steps(amax, dy, k_of, cols, coef, rho, z, terms):
    """Recover (Δs, Δλ, Δe, Δμ) of every constraint from gᵀΔy; return the largest step ≤ amax that keeps s, λ, e, μ
    ≥ 0. Adds Σ sΔλ + λΔs + eΔμ + μΔe and Σ ΔsΔλ + ΔeΔμ to terms[0], terms[1]: the complementarity after a step α is
    Σ sλ + eμ + α terms[0] + α² terms[1]."""
    for i in range(z.shape[0]):
        g = 0.0
        for v in range(cols.shape[1]):
            g += coef[i, v] * dy[k_of[i], cols[i, v]]
        amax = _step(amax, g, rho[i] > 0, z, i, terms)
    return amax


@jit
def box_steps(amax, dy, k_of, j_of, sign, rho, z, terms):
    """``steps`` of boxes."""
    for i in range(z.shape[0]):
        amax = _step(amax, sign[i] * dy[k_of[i], j_of[i]], rho[i] > 0, z, i, terms)
    return amax


@jit_inlined
def _take_step(alpha, z, i):
    """s, λ, e, μ of constraint i after the step α (stored)."""
    s = z[i, S] + alpha * z[i, DS]
    lam = z[i, LAM] + alpha * z[i, DL]
    e = z[i, E] + alpha * z[i, DE]
    mu = z[i, MU] + alpha * z[i, DM]
    z[i, S], z[i, LAM], z[i, E], z[i, MU] = s, lam, e, mu
    return s, lam, e, mu


@jit_inlined
def _weight(soft, z, i):
    """Constraint i's 1/λ, 1/μ (0 if hard), weight w and the predictor's complementarities (stored); returns w, ξ."""
    s, lam, e, mu = z[i, S], z[i, LAM], z[i, E], z[i, MU]
    il = 1.0 / lam
    im = 1.0 / mu if soft else 0.0
    w = 1.0 / (s * il + e * im)
    rl, rm = s * lam, e * mu
    xi = z[i, RS] - rl * il + (rm + e * z[i, RE]) * im
    z[i, IL], z[i, IM], z[i, W], z[i, XI], z[i, DL], z[i, DM] = il, im, w, xi, rl, rm
    return w, xi


@jit_inlined
def _corrector_xi(sigma_mu, z, i):
    """Constraint i's corrector complementarities sλ + ΔsΔλ − σμ, eμ + ΔeΔμ − σμ (stored in the Δλ, Δμ rows) and ξ."""
    rl = z[i, S] * z[i, LAM]
    rm = z[i, E] * z[i, MU]
    rl += z[i, DS] * z[i, DL] - sigma_mu
    rm += z[i, DE] * z[i, DM] - sigma_mu
    xi = z[i, RS] - rl * z[i, IL] + (rm + z[i, E] * z[i, RE]) * z[i, IM]
    z[i, XI], z[i, DL], z[i, DM] = xi, rl, rm
    return xi


@jit_inlined
def _step(amax, g, soft, z, i, terms):
    """Constraint i's step from g = gᵀΔy (stored), the step bound amax lowered to keep it interior, terms added."""
    s, lam, e, mu = z[i, S], z[i, LAM], z[i, E], z[i, MU]
    dl = z[i, W] * (g + z[i, XI])
    ds = (-z[i, DL] - s * dl) * z[i, IL]
    if amax * ds < -s:
        amax = -s / ds
    if amax * dl < -lam:
        amax = -lam / dl
    dm = de = 0.0
    if soft:
        dm = z[i, RE] - dl
        de = (-z[i, DM] - e * dm) * z[i, IM]
        if amax * de < -e:
            amax = -e / de
        if amax * dm < -mu:
            amax = -mu / dm
    z[i, DL], z[i, DS], z[i, DM], z[i, DE] = dl, ds, dm, de
    terms[0] += s * dl + lam * ds + e * dm + mu * de
    terms[1] += ds * dl + de * dm
    return amax
