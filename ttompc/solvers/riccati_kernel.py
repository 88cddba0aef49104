"""A primal-dual interior-point method for stage-wise QPs whose Newton systems are solved by a Riccati recursion,
compiled with numba. The whole solve is one call, so Python never runs inside an iteration.

The problem (stage k = 0..N, y_k = [x_k (NX), u_k (NU)]; stage N's u part is a dummy with unit cost):

    min  Σ_k ½ Σ_j Qd[k, j] y[k, j]² + q[k]ᵀ y_k  +  Σ_i ρ_i e_i
    s.t. x_{k+1} = A_k x_k + B_k u_k + c_k,   x_0 fixed,
         box i:  σ_i y[k_i, j_i] ≤ d_i + e_i,        row i:  Σ_w g[i, w] y[k_i, ri[i, w]] ≤ d_i + e_i,
         e_i ≥ 0 for soft constraints (ρ_i > 0); e_i = 0 for hard ones (ρ_i = 0).

Each constraint has a slack s = d − a(y) + e ≥ 0 with multiplier λ, and (soft) e ≥ 0 with multiplier μ = ρ − λ.
Eliminating s, e, λ, μ from the Newton system leaves per constraint a weight w = 1/(s/λ + e/μ) on gᵀΔy, so each
stage's Hessian gains Σ w g gᵀ and the remaining system (stage Hessians coupled by the dynamics) is solved by a
backward Riccati pass (P_k, K_k) and a forward rollout: O(N·(NX+NU)³) per iteration instead of a sparse LDLᵀ of
the whole KKT matrix. Mehrotra predictor-corrector steps reuse one factorisation per iteration.

NX and NU are compile-time constants (``numba.literally``) so the small dense loops unroll; one compilation per
(NX, NU), cached on disk.
"""

from __future__ import annotations

import numpy as np
from numba import literally, njit

_jit = njit(cache=True, error_model="numpy")  # no fastmath: it drops the NaN checks a breakdown needs


@_jit
def _chol(M, L, m):
    """L Lᵀ = M for an m×m SPD block (a pivot below 1e-14 is clamped: the barrier keeps M positive definite)."""
    for j in range(m):
        s = M[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        L[j, j] = np.sqrt(max(s, 1e-14))
        for i in range(j + 1, m):
            t = M[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / L[j, j]


@_jit
def _cho_solve(L, b, m):
    """b ← (L Lᵀ)⁻¹ b in place."""
    for i in range(m):
        t = b[i]
        for k in range(i):
            t -= L[i, k] * b[k]
        b[i] = t / L[i, i]
    for i in range(m - 1, -1, -1):
        t = b[i]
        for k in range(i + 1, m):
            t -= L[k, i] * b[k]
        b[i] = t / L[i, i]


@_jit
def solve_stage_qp(
    A, B, c, x0, Qd, q, bk, bj, bs, bd, brho, rk, ri, rg, rd, rrho, y, pi, tol, gap_tol, max_iter, NX, NU
):
    """Solve in place from the primal guess ``y`` (N+1, NX+NU) and multipliers ``pi`` (N, NX) of the dynamics.

    Returns (status, iterations, max residual, duality gap): status 0 converged (residuals ≤ tol, total
    complementarity ≤ gap_tol), 1 iteration limit, 2 numerical breakdown (a non-finite step), 3 stalled or broke
    down within 100× both tolerances (the best iterate is returned: accurate enough for the SCP's 1e-6 merit test)."""
    NX = literally(NX)
    NU = literally(NU)
    return _ipm(A, B, c, x0, Qd, q, bk, bj, bs, bd, brho, rk, ri, rg, rd, rrho, y, pi, tol, gap_tol, max_iter, NX, NU)


def compiled(n: int, nu: int, example: tuple):
    """The kernel specialised to (n, nu), as a direct entry point: calling ``solve_stage_qp`` from Python goes
    through numba's literal dispatch every time (measured: +4 ms per call, as much as the solve). ``example``
    (arguments of one solve) compiles it, or loads it from the disk cache, if needed."""
    for sig, result in solve_stage_qp.overloads.items():
        if getattr(sig[-2], "literal_value", None) == n and getattr(sig[-1], "literal_value", None) == nu:
            return result.entry_point  # type: ignore[attr-defined]  # (numba's stubs lack it)
    solve_stage_qp(*example)
    return compiled(n, nu, example)


@_jit
def _ipm(A, B, c, x0, Qd, q, bk, bj, bs, bd, brho, rk, ri, rg, rd, rrho, y, pi, tol, gap_tol, max_iter, n, nu):
    N = A.shape[0]
    W = ri.shape[1]
    bj2, bs2 = bj.reshape(-1, 1), bs.reshape(-1, 1)  # boxes as rows of width 1 for ``_steps``
    ny = n + nu
    nb, nr = bk.shape[0], rk.shape[0]
    # per constraint: slack s, multiplier lam, penalty slack e and its multiplier mu (soft only), value a = gᵀy
    s_b, l_b, e_b, m_b, a_b = np.empty(nb), np.empty(nb), np.zeros(nb), np.zeros(nb), np.empty(nb)
    s_r, l_r, e_r, m_r, a_r = np.empty(nr), np.empty(nr), np.zeros(nr), np.zeros(nr), np.empty(nr)
    for j in range(n):
        y[0, j] = x0[j]
    for j in range(nu):
        y[N, n + j] = 0.0
    _values(y, bk, bj, bs, rk, ri, rg, a_b, a_r)
    n_comp = _start(bd, brho, a_b, s_b, l_b, e_b, m_b) + _start(rd, rrho, a_r, s_r, l_r, e_r, m_r)
    # residuals, Newton weights and directions
    ry = np.zeros((N + 1, ny))  # stationarity
    rdyn = np.zeros((N, n))  # A x + B u + c − x⁺
    # per constraint: residuals (slack definition, e's stationarity), Newton weight w, ξ, 1/λ, 1/μ, the step
    wb, wr = np.zeros((10, nb)), np.zeros((10, nr))
    rs_b, re_b, w_b, xi_b, il_b, im_b, dl_b, ds_b, dm_b, de_b = (wb[0], wb[1], wb[2], wb[3], wb[4], wb[5], wb[6], wb[7],
                                                                   wb[8], wb[9])  # fmt: skip
    rs_r, re_r, w_r, xi_r, il_r, im_r, dl_r, ds_r, dm_r, de_r = (wr[0], wr[1], wr[2], wr[3], wr[4], wr[5], wr[6], wr[7],
                                                                   wr[8], wr[9])  # fmt: skip
    Qt = np.zeros((N + 1, ny, ny))  # stage Hessian + Σ w g gᵀ
    P = np.zeros((N + 1, n, n))  # Riccati cost-to-go Hessians
    S = np.zeros((N, nu, n))
    L = np.zeros((N, nu, nu))  # Cholesky factor of R + BᵀPB
    K = np.zeros((N, nu, n))  # feedback gains
    p = np.zeros((N + 1, n))
    rt = np.zeros((N + 1, ny))
    dy = np.zeros((N + 1, ny))
    dpi = np.zeros((N, n))
    PA, PB, Ruu = np.zeros((n, n)), np.zeros((n, nu)), np.zeros((nu, nu))
    tmp, tu = np.zeros(n), np.zeros(nu)
    res = gap = best_res = best_gap = best = np.inf
    y_best, pi_best = y.copy(), pi.copy()  # the iterate closest to the tolerances, by max(res/tol, gap/gap_tol)
    stale = 0  # iterations since it last improved
    for it in range(max_iter):
        # ---------------------------------------------------------------------------------------------- residuals
        for k in range(N + 1):
            for j in range(ny):
                ry[k, j] = Qd[k, j] * y[k, j] + q[k, j]
        for k in range(N):
            for a in range(n):
                t = c[k, a] - y[k + 1, a]
                for b in range(n):
                    t += A[k, a, b] * y[k, b]
                for b in range(nu):
                    t += B[k, a, b] * y[k, n + b]
                rdyn[k, a] = t
            for b in range(n):
                t = 0.0
                for a in range(n):
                    t += A[k, a, b] * pi[k, a]
                ry[k, b] += t
                ry[k + 1, b] -= pi[k, b]
            for b in range(nu):
                t = 0.0
                for a in range(n):
                    t += B[k, a, b] * pi[k, a]
                ry[k, n + b] += t
        for i in range(nb):
            ry[bk[i], bj[i]] += bs[i] * l_b[i]
            rs_b[i] = s_b[i] - bd[i] + a_b[i] - e_b[i]
            re_b[i] = brho[i] - l_b[i] - m_b[i] if brho[i] > 0 else 0.0
        for i in range(nr):
            for w in range(W):
                ry[rk[i], ri[i, w]] += rg[i, w] * l_r[i]
            rs_r[i] = s_r[i] - rd[i] + a_r[i] - e_r[i]
            re_r[i] = rrho[i] - l_r[i] - m_r[i] if rrho[i] > 0 else 0.0
        for j in range(n):
            ry[0, j] = 0.0  # x_0 is fixed
        for j in range(nu):
            ry[N, n + j] = 0.0  # the dummy control of the last stage
        gap = 0.0
        for i in range(nb):
            gap += s_b[i] * l_b[i] + e_b[i] * m_b[i]
        for i in range(nr):
            gap += s_r[i] * l_r[i] + e_r[i] * m_r[i]
        mu = gap / max(n_comp, 1)
        res = max(np.max(np.abs(ry)), np.max(np.abs(rdyn)) if N else 0.0)
        if nb:
            res = max(res, np.max(np.abs(rs_b)), np.max(np.abs(re_b)))
        if nr:
            res = max(res, np.max(np.abs(rs_r)), np.max(np.abs(re_r)))
        if res <= tol and gap <= gap_tol:
            return 0, it, res, gap
        # Near the optimum the Newton systems lose accuracy (weights λ/s → 0 or ∞): the residual can stall or grow
        # while the gap falls, up to a non-finite step. Keep the best iterate; stop with it once it is within 100×
        # both tolerances and has not improved for 3 iterations, or on a breakdown.
        score = max(res / tol, gap / gap_tol)
        if score < best:
            best, best_res, best_gap, stale = score, res, gap, 0
            y_best[:, :] = y
            pi_best[:, :] = pi
        else:
            stale += 1
        if not np.isfinite(score) or (stale >= 3 and best <= 100.0):
            y[:, :] = y_best
            pi[:, :] = pi_best
            return (3 if best <= 100.0 else 2), it, best_res, best_gap
        # ---------------------------------------------------------------------------------------------- factorise
        for i in range(nb):
            il_b[i] = 1.0 / l_b[i]
            im_b[i] = 1.0 / m_b[i] if brho[i] > 0 else 0.0
            w_b[i] = 1.0 / (s_b[i] * il_b[i] + e_b[i] * im_b[i])
        for i in range(nr):
            il_r[i] = 1.0 / l_r[i]
            im_r[i] = 1.0 / m_r[i] if rrho[i] > 0 else 0.0
            w_r[i] = 1.0 / (s_r[i] * il_r[i] + e_r[i] * im_r[i])
        for k in range(N + 1):
            for a in range(ny):
                for b in range(ny):
                    Qt[k, a, b] = 0.0
                Qt[k, a, a] = Qd[k, a] + 1e-10
        for i in range(nb):
            Qt[bk[i], bj[i], bj[i]] += w_b[i]
        for i in range(nr):
            k = rk[i]
            for a in range(W):
                ga = w_r[i] * rg[i, a]
                for b in range(W):
                    Qt[k, ri[i, a], ri[i, b]] += ga * rg[i, b]
        for a in range(n):
            for b in range(n):
                P[N, a, b] = Qt[N, a, b]
        for k in range(N - 1, -1, -1):
            for a in range(n):  # PA = P⁺A, PB = P⁺B
                for b in range(n):
                    t = 0.0
                    for e in range(n):
                        t += P[k + 1, a, e] * A[k, e, b]
                    PA[a, b] = t
                for b in range(nu):
                    t = 0.0
                    for e in range(n):
                        t += P[k + 1, a, e] * B[k, e, b]
                    PB[a, b] = t
            for a in range(nu):  # Ruu = R + BᵀP⁺B, S = Q_ux + BᵀP⁺A
                for b in range(nu):
                    t = Qt[k, n + a, n + b]
                    for e in range(n):
                        t += B[k, e, a] * PB[e, b]
                    Ruu[a, b] = t
                for b in range(n):
                    t = Qt[k, n + a, b]
                    for e in range(n):
                        t += B[k, e, a] * PA[e, b]
                    S[k, a, b] = t
            _chol(Ruu, L[k], nu)
            for b in range(n):  # K = −Ruu⁻¹ S
                for a in range(nu):
                    tu[a] = S[k, a, b]
                _cho_solve(L[k], tu, nu)
                for a in range(nu):
                    K[k, a, b] = -tu[a]
            for a in range(n):  # P = Q_xx + AᵀP⁺A + SᵀK, symmetrised
                for b in range(a, n):
                    t = Qt[k, a, b]
                    for e in range(n):
                        t += A[k, e, a] * PA[e, b]
                    for e in range(nu):
                        t += S[k, e, a] * K[k, e, b]
                    P[k, a, b] = t
                    P[k, b, a] = t
        # ------------------------------------------------------------------------- predictor, then corrector step
        sigma_mu = 0.0
        alpha = 1.0
        for corrector in range(2):
            _rhs(corrector, sigma_mu, s_b, l_b, e_b, m_b, rs_b, re_b, il_b, im_b, ds_b, dl_b, de_b, dm_b, xi_b)
            _rhs(corrector, sigma_mu, s_r, l_r, e_r, m_r, rs_r, re_r, il_r, im_r, ds_r, dl_r, de_r, dm_r, xi_r)
            for k in range(N + 1):
                for j in range(ny):
                    rt[k, j] = ry[k, j]
            for i in range(nb):
                rt[bk[i], bj[i]] += bs[i] * w_b[i] * xi_b[i]
            for i in range(nr):
                f = w_r[i] * xi_r[i]
                for w in range(W):
                    rt[rk[i], ri[i, w]] += rg[i, w] * f
            for a in range(n):  # backward pass: feedforward terms
                p[N, a] = rt[N, a]
            for k in range(N - 1, -1, -1):
                for a in range(n):  # tmp = P⁺ rdyn + p⁺
                    t = p[k + 1, a]
                    for e in range(n):
                        t += P[k + 1, a, e] * rdyn[k, e]
                    tmp[a] = t
                for a in range(nu):
                    t = rt[k, n + a]
                    for e in range(n):
                        t += B[k, e, a] * tmp[e]
                    tu[a] = t
                _cho_solve(L[k], tu, nu)
                for a in range(nu):
                    dy[k, n + a] = -tu[a]
                for a in range(n):
                    t = rt[k, a]
                    for e in range(n):
                        t += A[k, e, a] * tmp[e]
                    for e in range(nu):
                        t -= S[k, e, a] * tu[e]
                    p[k, a] = t
            for a in range(n):  # forward pass
                dy[0, a] = 0.0
            for k in range(N):
                for a in range(nu):
                    t = dy[k, n + a]
                    for b in range(n):
                        t += K[k, a, b] * dy[k, b]
                    dy[k, n + a] = t
                for a in range(n):
                    t = rdyn[k, a]
                    for b in range(n):
                        t += A[k, a, b] * dy[k, b]
                    for b in range(nu):
                        t += B[k, a, b] * dy[k, n + b]
                    dy[k + 1, a] = t
            amax = _steps(1.0, bk, bj2, bs2, dy, w_b, xi_b, s_b, l_b, e_b, m_b, re_b, brho, il_b, im_b,
                          ds_b, dl_b, de_b, dm_b)  # fmt: skip
            amax = _steps(amax, rk, ri, rg, dy, w_r, xi_r, s_r, l_r, e_r, m_r, re_r, rrho, il_r, im_r,
                          ds_r, dl_r, de_r, dm_r)  # fmt: skip
            if corrector == 0:  # Mehrotra's centring from the affine step's complementarity
                gap_aff = _gap(amax, s_b, l_b, e_b, m_b, ds_b, dl_b, de_b, dm_b)
                gap_aff += _gap(amax, s_r, l_r, e_r, m_r, ds_r, dl_r, de_r, dm_r)
                sigma_mu = (gap_aff / max(n_comp, 1) / mu) ** 3 * mu
            else:
                alpha = min(1.0, 0.995 * amax)
        for k in range(N):  # Δπ_k = P_{k+1} Δx_{k+1} + p_{k+1}
            for a in range(n):
                t = p[k + 1, a]
                for b in range(n):
                    t += P[k + 1, a, b] * dy[k + 1, b]
                dpi[k, a] = t
        # ---------------------------------------------------------------------------------------------- update
        for k in range(N + 1):
            for j in range(ny):
                y[k, j] += alpha * dy[k, j]
        for k in range(N):
            for a in range(n):
                pi[k, a] += alpha * dpi[k, a]
        for i in range(nb):
            s_b[i] += alpha * ds_b[i]
            l_b[i] += alpha * dl_b[i]
            e_b[i] += alpha * de_b[i]
            m_b[i] += alpha * dm_b[i]
        for i in range(nr):
            s_r[i] += alpha * ds_r[i]
            l_r[i] += alpha * dl_r[i]
            e_r[i] += alpha * de_r[i]
            m_r[i] += alpha * dm_r[i]
        _values(y, bk, bj, bs, rk, ri, rg, a_b, a_r)
    if best <= 100.0:
        y[:, :] = y_best
        pi[:, :] = pi_best
        return 3, max_iter, best_res, best_gap
    return 1, max_iter, res, gap


@_jit
def _values(y, bk, bj, bs, rk, ri, rg, a_b, a_r):
    for i in range(bk.shape[0]):
        a_b[i] = bs[i] * y[bk[i], bj[i]]
    for i in range(rk.shape[0]):
        t = 0.0
        for w in range(ri.shape[1]):
            t += rg[i, w] * y[rk[i], ri[i, w]]
        a_r[i] = t


@_jit
def _start(d, rho, a, s, lam, e, mu):
    """A strictly interior start: s, e ≥ 0.1 with s − e = d − a for soft rows (primal residual 0), λ = μ = ρ/2, and
    s ≥ 0.1, λ = 1 for hard rows. (Measured on the 89 subproblems of REL + SCP on free-flyer and quadrotor seeds
    0–5: 0.1 takes 20.1 and 9.7 iterations on average, 1.0 21.1 and 11.4 with 3 breakdowns near the optimum, 10.0
    23.0 and 13.6.)"""
    count = 0
    for i in range(d.shape[0]):
        v = d[i] - a[i]
        if rho[i] > 0:
            s[i] = max(v, 0.0) + 0.1
            e[i] = s[i] - v
            lam[i] = 0.5 * rho[i]
            mu[i] = 0.5 * rho[i]
            count += 2
        else:
            s[i] = max(v, 0.1)
            lam[i] = 1.0
            count += 1
    return count


@_jit
def _rhs(corrector, sigma_mu, s, lam, e, mu, rs, re, il, im, ds, dl, de, dm, xi):
    """Complementarity right-hand sides (stored in dl, dm until ``_steps``) and ξ, with Δλ = w (gᵀΔy + ξ)."""
    for i in range(s.shape[0]):
        rl = s[i] * lam[i]
        rm = e[i] * mu[i]
        if corrector:
            rl += ds[i] * dl[i] - sigma_mu
            rm += de[i] * dm[i] - sigma_mu
        xi[i] = rs[i] - rl * il[i] + (rm + e[i] * re[i]) * im[i]
        dl[i] = rl
        dm[i] = rm


@_jit
def _steps(amax, k_of, cols, coef, dy, w, xi, s, lam, e, mu, re, rho, il, im, ds, dl, de, dm):
    """Recover (Δs, Δλ, Δe, Δμ) of every constraint from gᵀΔy = Σ_v coef[i, v]·Δy[k_of[i], cols[i, v]] (a box is a
    row of width 1); return the largest step ≤ amax that keeps them ≥ 0."""
    for i in range(s.shape[0]):
        g = 0.0
        for v in range(cols.shape[1]):
            g += coef[i, v] * dy[k_of[i], cols[i, v]]
        dli = w[i] * (g + xi[i])
        dsi = (-dl[i] - s[i] * dli) * il[i]
        if amax * dsi < -s[i]:
            amax = -s[i] / dsi
        if amax * dli < -lam[i]:
            amax = -lam[i] / dli
        dmi = dei = 0.0
        if rho[i] > 0:
            dmi = re[i] - dli
            dei = (-dm[i] - e[i] * dmi) * im[i]
            if amax * dei < -e[i]:
                amax = -e[i] / dei
            if amax * dmi < -mu[i]:
                amax = -mu[i] / dmi
        dl[i], ds[i], dm[i], de[i] = dli, dsi, dmi, dei
    return amax


@_jit
def _gap(alpha, s, lam, e, mu, ds, dl, de, dm):
    total = 0.0
    for i in range(s.shape[0]):
        total += (s[i] + alpha * ds[i]) * (lam[i] + alpha * dl[i]) + (e[i] + alpha * de[i]) * (mu[i] + alpha * dm[i])
    return total
