"""The Riccati kernel's terminal cone (``riccati_kernel``): u = (τ, cw∘(x_N − cx)) ∈ SOC at cost τ, τ = y[N, n]
(stage N's first dummy control), cw and cx the arrays of a ``riccati_qp.TerminalCone``.

The cone takes Nesterov-Todd scaling; τ is eliminated from stage N in closed form (``factor``) and the cone's steps
are taken in the scaled space, where λ sits well inside the cone while s and z approach its boundary: the step
lengths and Δz then stay accurate to rounding (why both: docs/design.md).

The cone's state lives in the rows of ``kc`` (STATE_ROWS, n + 1), named below: s and z, u, rp = u − s, λ = Wz = W⁻¹s,
v (λ∘v = the complementarity right-hand side), t, w̄, the step Δs, Δz, Δs̃ = W⁻¹Δs, Δz̃ = WΔz, the affine step's
Δs̃, Δz̃, and scratch; its scaling in ``kw`` (3, n + 1, n + 1): W, W⁻¹ and W⁻² (W = η W̄, W̄ = [[w̄₀, w̄₁ᵀ], [w̄₁,
I + w̄₁w̄₁ᵀ/(1 + w̄₀)]], w̄₀² − ‖w̄₁‖² = 1).
"""

from __future__ import annotations

import numpy as np

from ttompc.solvers.backends.riccati_jit import jit

CS, CZ, CU, CRP, CLAM, CV, CT, CWB, CDS, CDZ, CST, CZT, CSA, CZA, CTMP = range(15)
STATE_ROWS = 15  # rows of ``kc``


@jit
def start(y, N, n, cw, cx, kc):
    """s = u at y pushed inside the cone (s₀ = max(u₀, ‖u₁‖) + 1), z = Js / det(s): s∘z = e, a centred start."""
    u, s, z = kc[CU], kc[CS], kc[CZ]
    point(y, N, n, cw, cx, u)
    norm1 = 0.0
    for j in range(1, n + 1):
        norm1 += u[j] * u[j]
        s[j] = u[j]
    s[0] = max(u[0], np.sqrt(norm1)) + 1.0
    det = s[0] * s[0] - norm1
    for j in range(n + 1):
        z[j] = (s[j] if j == 0 else -s[j]) / det


@jit
def point(y, N, n, cw, cx, u):
    """u = (τ, cw∘(x_N − cx)): the cone's point at y."""
    u[0] = y[N, n]
    for a in range(n):
        u[a + 1] = cw[a] * (y[N, a] - cx[a])


@jit
def residuals(gap, y, ry, N, n, cw, cx, kc):
    """rp = u − s; add −Fᵀz to the stationarity residual (F: (x_N, τ) → u); return gap + sᵀz and max |rp| (NaN if
    any is not finite)."""
    u, s, z, rp = kc[CU], kc[CS], kc[CZ], kc[CRP]
    point(y, N, n, cw, cx, u)
    ry[N, n] -= z[0]
    res = probe = 0.0
    for j in range(n + 1):
        rp[j] = u[j] - s[j]
        res = max(res, abs(rp[j]))
        probe += rp[j]
        gap += s[j] * z[j]
        if j > 0:
            ry[N, j - 1] -= cw[j - 1] * z[j]
    return gap, res + 0.0 * probe


@jit
def factor(PN, cw, kc, kw, pvec):
    """The scaling at s, z, then τ eliminated from stage N in closed form: PN += D S D with S = η⁻²(I + 2w̄₁w̄₁ᵀ)⁻¹
    the Schur complement of W⁻² (D = diag(cw)), pvec = −D W⁻²₁₀ / W⁻²₀₀; returns 1 / W⁻²₀₀. Forming S from W⁻²
    instead cancels digits of order η⁻²w̄₀² (the failures measured in docs/design.md)."""
    n = cw.shape[0]
    eta = nt_scaling(kc[CS], kc[CZ], kw[0], kw[1], kw[2], kc[CLAM], kc[CWB])
    wb = kc[CWB]
    w0 = wb[0]
    den = 2.0 * w0 * w0 - 1.0  # = 1 + 2‖w̄₁‖² ≥ 1
    nw2 = 0.0
    for a in range(n):
        nw2 += wb[a + 1] * wb[a + 1]
    inv_nw2 = 1.0 / nw2 if nw2 > 0.0 else 0.0
    for a in range(n):
        pvec[a] = cw[a] * 2.0 * w0 * wb[a + 1] / den
        for b in range(n):  # S = η⁻²((I − ŵŵᵀ) + ŵŵᵀ / den), ŵ = w̄₁/‖w̄₁‖
            sab = (1.0 if a == b else 0.0) + wb[a + 1] * wb[b + 1] * inv_nw2 * (1.0 / den - 1.0)
            PN[a, b] += cw[a] * sab * cw[b] / (eta * eta)
    return eta * eta / den


@jit
def nt_scaling(s, z, W, Wi, Wi2, lam, wbar):
    """The Nesterov-Todd scaling of one second-order cone at interior s, z: W (symmetric, W z = W⁻¹ s), W⁻¹, W⁻²
    (closed forms), λ = W z and w̄; returns η."""
    m = s.shape[0]
    sJs, zJz = s[0] * s[0], z[0] * z[0]
    for j in range(1, m):
        sJs -= s[j] * s[j]
        zJz -= z[j] * z[j]
    sJs, zJz = max(sJs, 1e-300), max(zJz, 1e-300)
    ss, zs = np.sqrt(sJs), np.sqrt(zJz)
    dot = s[0] * z[0]
    for j in range(1, m):
        dot += s[j] * z[j]
    gamma = np.sqrt(max(0.5 * (1.0 + dot / (ss * zs)), 1e-300))
    eta = np.sqrt(ss / zs)
    w0 = (s[0] / ss + z[0] / zs) / (2.0 * gamma)
    wbar[0] = w0
    for j in range(1, m):
        wbar[j] = (s[j] / ss - z[j] / zs) / (2.0 * gamma)
    for a in range(m):
        for b in range(m):
            if a == 0 and b == 0:
                v = w0
                vi = w0
            elif a == 0 or b == 0:
                v = wbar[a + b]
                vi = -v
            else:
                v = wbar[a] * wbar[b] / (1.0 + w0) + (1.0 if a == b else 0.0)
                vi = v
            W[a, b] = v * eta
            Wi[a, b] = vi / eta
    for a in range(m):
        t = 0.0
        for b in range(m):
            t += W[a, b] * z[b]
        lam[a] = t
        for b in range(m):  # W⁻² = η⁻²[[2w̄₀² − 1, −2w̄₀w̄₁ᵀ], [−2w̄₀w̄₁, I + 2w̄₁w̄₁ᵀ]]
            if a == 0 and b == 0:
                v = 2.0 * w0 * w0 - 1.0
            elif a == 0 or b == 0:
                v = -2.0 * w0 * wbar[a + b]
            else:
                v = (1.0 if a == b else 0.0) + 2.0 * wbar[a] * wbar[b]
            Wi2[a, b] = v / (eta * eta)
    return eta


@jit
def rhs(corrector, sigma_mu, rt, N, n, cw, kc, kw):
    """λ∘(Δs̃ + Δz̃) = r_c with r_c = −λ∘λ (the corrector adds σμe − Δs̃_a∘Δz̃_a): v = λ⁻¹∘r_c (the Jordan
    inverse), t = W⁻¹v − W⁻²rp, and rt −= Fᵀt."""
    m = n + 1
    lam, rc, v, t, a, b = kc[CLAM], kc[CTMP], kc[CV], kc[CT], kc[CSA], kc[CZA]
    rc[0] = 0.0
    for j in range(m):
        rc[0] -= lam[j] * lam[j]
    for j in range(1, m):
        rc[j] = -2.0 * lam[0] * lam[j]
    if corrector:
        dot = 0.0
        for j in range(m):
            dot += a[j] * b[j]
        rc[0] += sigma_mu - dot
        for j in range(1, m):
            rc[j] -= a[0] * b[j] + b[0] * a[j]
    # v = λ⁻¹∘r_c: v0 = (λ0 r0 − λ1ᵀr1) / (λ0² − ‖λ1‖²), v1 = (r1 − v0 λ1) / λ0
    det, num = lam[0] * lam[0], lam[0] * rc[0]
    for j in range(1, m):
        det -= lam[j] * lam[j]
        num -= lam[j] * rc[j]
    v[0] = num / det
    for j in range(1, m):
        v[j] = (rc[j] - v[0] * lam[j]) / lam[0]
    Wi, Wi2, rp = kw[1], kw[2], kc[CRP]
    for i in range(m):
        acc = 0.0
        for j in range(m):
            acc += Wi[i, j] * v[j] - Wi2[i, j] * rp[j]
        t[i] = acc
    rt[N, n] -= t[0]
    for i in range(n):
        rt[N, i] -= cw[i] * t[i + 1]


@jit
def steps(amax, corrector, dy, rt, N, n, cw, m00inv, pvec, kc, kw):
    """Δτ from Δx_N (the closed-form elimination), Δu = FΔy, Δs = Δu + rp, then in the scaled space Δs̃ = W⁻¹Δs,
    Δz̃ = v − Δs̃ and Δz = W⁻¹Δz̃; returns the largest step ≤ amax that keeps λ + αΔs̃ and λ + αΔz̃ (so s and z) in
    the cone. The affine step keeps its Δs̃, Δz̃ for the corrector."""
    m = n + 1
    u, ds, dz, st, zt, v, rp, Wi = kc[CU], kc[CDS], kc[CDZ], kc[CST], kc[CZT], kc[CV], kc[CRP], kw[1]
    t = -rt[N, n] * m00inv
    for a in range(n):
        t += pvec[a] * dy[N, a]
    dy[N, n] = t
    u[0] = t
    for a in range(n):
        u[a + 1] = cw[a] * dy[N, a]
    for j in range(m):
        ds[j] = u[j] + rp[j]
    for j in range(m):
        t = 0.0
        for b in range(m):
            t += Wi[j, b] * ds[b]
        st[j] = t
        zt[j] = v[j] - t
    for j in range(m):
        t = 0.0
        for b in range(m):
            t += Wi[j, b] * zt[b]
        dz[j] = t
    lam = kc[CLAM]
    amax = max_step(lam, st, max_step(lam, zt, amax))
    if corrector == 0:
        for j in range(m):
            kc[CSA, j], kc[CZA, j] = st[j], zt[j]
    return amax


@jit
def step_gap(total, alpha, kc):
    """total + sᵀz after a step α, from the scaled point: (λ + αΔs̃)ᵀ(λ + αΔz̃)."""
    for j in range(kc.shape[1]):
        total += (kc[CLAM, j] + alpha * kc[CST, j]) * (kc[CLAM, j] + alpha * kc[CZT, j])
    return total


@jit
def update(alpha, n, kc):
    """Take the step α."""
    for j in range(n + 1):
        kc[CS, j] += alpha * kc[CDS, j]
        kc[CZ, j] += alpha * kc[CDZ, j]


@jit
def max_step(x, d, amax):
    """The largest α ≤ amax with x + αd in the second-order cone (x interior): the first positive root of
    ‖x + αd‖_J² = aα² + 2bα + c (J = diag(1, −I))."""
    m = x.shape[0]
    a, b, c = d[0] * d[0], x[0] * d[0], x[0] * x[0]
    for j in range(1, m):
        a -= d[j] * d[j]
        b -= x[j] * d[j]
        c -= x[j] * x[j]
    alpha = np.inf
    if abs(a) < 1e-300:
        if b < 0:
            alpha = -c / (2.0 * b)
    else:
        disc = b * b - a * c
        if a < 0:
            alpha = (-b - np.sqrt(max(disc, 0.0))) / a
        elif b < 0 and disc >= 0:
            alpha = (-b - np.sqrt(disc)) / a
    if x[0] + min(alpha, amax) * d[0] < 0:  # (not reached from an interior x: the other nappe)
        alpha = -x[0] / d[0]
    return min(amax, alpha)
