"""A primal-dual interior-point method for stage-wise QPs whose Newton systems are solved by a Riccati recursion,
compiled with numba. The whole solve is one call, so Python never runs inside an iteration.

The problem (stage k = 0..N, y_k = [x_k (NX), u_k (NU)]; stage N's u part is a dummy with unit cost):

    min  Σ_k ½ Σ_j Qd[k, j] y[k, j]² + q[k]ᵀ y_k  +  Σ_i ρ_i e_i
    s.t. x_{k+1} = A_k x_k + B_k u_k + c_k,   x_0 fixed,
         box i:  σ_i y[k_i, j_i] ≤ d_i + e_i,        row i:  Σ_w g[i, w] y[k_i, ri[i, w]] ≤ d_i + e_i,
         e_i ≥ 0 for soft constraints (ρ_i > 0); e_i = 0 for hard ones (ρ_i = 0);
         optionally one second-order cone τ ≥ ‖cw∘(x_N − cx)‖₂ on τ = y[N, NX], stage N's first dummy control
         (the caller prices τ through q and gives it no Qd): an MPC window's soft terminal term.

Each constraint has a slack s = d − a(y) + e ≥ 0 with multiplier λ, and (soft) e ≥ 0 with multiplier μ = ρ − λ.
Eliminating s, e, λ, μ from the Newton system leaves per constraint a weight w = 1/(s/λ + e/μ) on gᵀΔy, so each
stage's Hessian gains Σ w g gᵀ and the remaining system (stage Hessians coupled by the dynamics) is solved by a
backward Riccati pass (P_k, K_k) and a forward rollout: O(N·(NX+NU)³) per iteration instead of a sparse LDLᵀ of
the whole KKT matrix. Mehrotra predictor-corrector steps reuse one factorisation per iteration. The cone takes
Nesterov-Todd scaling; τ is eliminated from stage N in closed form and the cone's steps are taken in the scaled
space (below ``_ipm``; why: docs/design.md).

NX and NU are compile-time constants (``numba.literally``) so the small dense loops unroll; one compilation per
(NX, NU), cached on disk: once per machine (where the cache lives, and the times: docs/design.md).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

import numpy as np
from numba import literally, njit


def _jit(func: Callable) -> Any:  # a numba dispatcher
    """``njit`` with numba's on-disk cache (no fastmath: it drops the NaN checks a breakdown needs). Where no cache
    folder is writable (``NUMBA_CACHE_DIR``, the package's ``__pycache__``, the user's cache folder) numba refuses to
    decorate: the kernel then compiles in every process that uses it instead of failing to import, with a warning."""
    try:
        return njit(cache=True, error_model="numpy")(func)
    except RuntimeError as err:
        if "no locator available" not in str(err):
            raise
        warnings.warn(
            "the riccati backend's kernel cannot be cached (no writable numba cache folder): it compiles in every "
            "process (~10-20 s); set NUMBA_CACHE_DIR to a writable folder to compile it once",
            RuntimeWarning,
            stacklevel=1,  # this line, not each decorated function's: shown once
        )
        return njit(error_model="numpy")(func)


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
    A, B, c, x0, Qd, q, bk, bj, bs, bd, brho, rk, ri, rg, rd, rrho, cw, cx, y, pi, tol, gap_tol, max_iter, NX, NU
):
    """Solve in place from the primal guess ``y`` (N+1, NX+NU) and multipliers ``pi`` (N, NX) of the dynamics;
    ``cw``, ``cx`` (NX,) the terminal cone's weights and centre, both empty for none.

    Returns (status, iterations, max residual, duality gap): status 0 converged (residuals ≤ tol, total
    complementarity ≤ gap_tol), 1 iteration limit, 2 numerical breakdown (a non-finite step), 3 stalled or broke
    down within 100× both tolerances (the best iterate is returned: accurate enough for the SCP's 1e-6 merit test)."""
    NX = literally(NX)
    NU = literally(NU)
    return _ipm(
        A, B, c, x0, Qd, q, bk, bj, bs, bd, brho, rk, ri, rg, rd, rrho, cw, cx, y, pi, tol, gap_tol, max_iter, NX, NU
    )


_ENTRY: dict[tuple[int, int], Callable] = {}  # (NX, NU) -> the compiled specialisation, called directly


def solve(*args):
    """``solve_stage_qp(*args)`` without numba's literal dispatch, which calling it from Python re-enters every time
    (as costly as the solve; measured in docs/design.md): the first call per (NX, NU) in a process goes through the
    dispatcher (compiling the kernel or loading it from the disk cache), later ones through its entry point."""
    n, nu = args[-2], args[-1]
    entry = _ENTRY.get((n, nu))
    if entry is not None:
        return entry(*args)
    from ttompc.progress import status

    status(f"riccati backend: loading its kernel for {n} states and {nu} controls (compiled once per machine, ~20 s)")
    out = solve_stage_qp(*args)
    for sig, result in solve_stage_qp.overloads.items():
        if getattr(sig[-2], "literal_value", None) == n and getattr(sig[-1], "literal_value", None) == nu:
            _ENTRY[(n, nu)] = result.entry_point
    return out


@_jit
def _ipm(A, B, c, x0, Qd, q, bk, bj, bs, bd, brho, rk, ri, rg, rd, rrho, cw, cx, y, pi, tol, gap_tol, max_iter, n, nu):
    N = A.shape[0]
    ny = n + nu
    # the terminal cone (cw non-empty, MPC windows): u = (τ, cw∘(x_N − cx)) ∈ SOC at cost τ, τ = y[N, n] (stage
    # N's first dummy control); its state in the rows of ``kc`` (named below ``_ipm``), its scaling in ``kw``
    cone = cw.shape[0] > 0
    kc, kw, pvec = np.zeros((15, n + 1)), np.zeros((3, n + 1, n + 1)), np.zeros(n)
    m00inv = 0.0
    nb, nr = bk.shape[0], rk.shape[0]
    bj2, bs2 = bj.reshape(-1, 1), bs.reshape(-1, 1)  # boxes are rows of width 1: one code path for both
    # per constraint: slack s, multiplier λ, penalty slack e and its multiplier μ (soft only), residuals of the slack
    # definition (rs) and of e's stationarity (re), 1/λ, 1/μ, the Newton weight w, ξ, and the step (Δs, Δλ, Δe, Δμ)
    cb, cr = np.zeros((14, nb)), np.zeros((14, nr))
    for j in range(n):
        y[0, j] = x0[j]
    for j in range(nu):
        y[N, n + j] = 0.0
    n_comp = _start(y, bk, bj2, bs2, bd, brho, cb) + _start(y, rk, ri, rg, rd, rrho, cr)
    if cone:
        _cone_start(y, N, n, cw, cx, kc)
        n_comp += 1
    ry = np.zeros((N + 1, ny))  # stationarity
    rdyn = np.zeros((N, n))  # A x + B u + c − x⁺
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
        res = probe = 0.0  # probe: the sum of every residual, non-finite iff one of them is (max() skips NaN)
        for k in range(N):
            for a in range(n):
                t = c[k, a] - y[k + 1, a]
                for b in range(n):
                    t += A[k, a, b] * y[k, b]
                for b in range(nu):
                    t += B[k, a, b] * y[k, n + b]
                rdyn[k, a] = t
                res = max(res, abs(t))
                probe += t
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
        gap_b, res_b = _residuals(y, ry, bk, bj2, bs2, bd, brho, cb)
        gap_r, res_r = _residuals(y, ry, rk, ri, rg, rd, rrho, cr)
        gap, res = gap_b + gap_r, max(res, res_b, res_r)
        if cone:
            gap, res_c = _cone_residuals(gap, y, ry, N, n, cw, cx, kc)
            res = max(res, res_c)
        for j in range(n):
            ry[0, j] = 0.0  # x_0 is fixed
        for j in range(1 if cone else 0, nu):
            ry[N, n + j] = 0.0  # the dummy controls of the last stage (τ is the first where there is a cone)
        for k in range(N + 1):
            for j in range(ny):
                res = max(res, abs(ry[k, j]))
                probe += ry[k, j]
        res += 0.0 * probe
        mu = gap / max(n_comp, 1)
        if res <= tol and gap <= gap_tol:
            return 0, it, res, gap
        # Near the optimum the Newton systems lose accuracy (weights λ/s → 0 or ∞): the residual can stall or grow
        # while the gap falls, up to a non-finite step. Keep the best iterate; stop with it once it is within 100×
        # both tolerances and has not improved for 3 iterations, or on a breakdown.
        score = max(res / tol, gap / gap_tol)
        if score < best:  # (False for NaN: a breakdown never becomes the best iterate)
            best, best_res, best_gap, stale = score, res, gap, 0
            y_best[:, :] = y
            pi_best[:, :] = pi
        else:
            stale += 1
        if not np.isfinite(res + gap) or (stale >= 3 and best <= 100.0):
            y[:, :] = y_best
            pi[:, :] = pi_best
            return (3 if best <= 100.0 else 2), it, best_res, best_gap
        # ---------------------------------------------------------------------------------------------- factorise
        for k in range(N + 1):
            for a in range(ny):
                for b in range(ny):
                    Qt[k, a, b] = 0.0
                Qt[k, a, a] = Qd[k, a] + 1e-10
        _weights(Qt, bk, bj2, bs2, brho, cb)
        _weights(Qt, rk, ri, rg, rrho, cr)
        for a in range(n):
            for b in range(n):
                P[N, a, b] = Qt[N, a, b]
        if cone:
            m00inv = _cone_factor(P[N], cw, kc, kw, pvec)
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
            for k in range(N + 1):
                for j in range(ny):
                    rt[k, j] = ry[k, j]
            _rhs(corrector, sigma_mu, rt, bk, bj2, bs2, cb)
            _rhs(corrector, sigma_mu, rt, rk, ri, rg, cr)
            if cone:
                _cone_rhs(corrector, sigma_mu, rt, N, n, cw, kc, kw)
            for a in range(n):  # backward pass: feedforward terms
                p[N, a] = rt[N, a] + (pvec[a] * rt[N, n] if cone else 0.0)
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
            amax = _steps(1.0, dy, bk, bj2, bs2, brho, cb)
            amax = _steps(amax, dy, rk, ri, rg, rrho, cr)
            if cone:
                amax = _cone_steps(amax, corrector, dy, rt, N, n, cw, m00inv, pvec, kc, kw)
            if corrector == 0:  # Mehrotra's centring from the affine step's complementarity
                gap_aff = _gap(amax, cb) + _gap(amax, cr)
                if cone:
                    gap_aff = _cone_gap(gap_aff, amax, kc)
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
        _update(alpha, cb)
        _update(alpha, cr)
        if cone:
            for j in range(n + 1):
                kc[_CS, j] += alpha * kc[_CDS, j]
                kc[_CZ, j] += alpha * kc[_CDZ, j]
    if best <= 100.0:
        y[:, :] = y_best
        pi[:, :] = pi_best
        return 3, max_iter, best_res, best_gap
    return 1, max_iter, res, gap


# Constraint families (boxes, rows): g_iᵀy = Σ_v coef[i, v]·y[k_of[i], cols[i, v]] ≤ d_i (+ e_i if ρ_i > 0); the
# per-constraint state lives in the rows of one (14, m) array ``z``, named below. Each helper is one pass.
_S, _LAM, _E, _MU, _RS, _RE, _IL, _IM, _W, _XI, _DS, _DL, _DE, _DM = range(14)


@_jit
def _start(y, k_of, cols, coef, d, rho, z):
    """A strictly interior start: s, e ≥ 0.1 with s − e = d − gᵀy for soft rows (primal residual 0), λ = μ = ρ/2, and
    s ≥ 0.1, λ = 1 for hard rows. Returns the number of complementarity pairs. (Why 0.1: measured in docs/design.md.)"""
    count = 0
    for i in range(d.shape[0]):
        a = 0.0
        for v in range(cols.shape[1]):
            a += coef[i, v] * y[k_of[i], cols[i, v]]
        gap = d[i] - a
        if rho[i] > 0:
            z[_S, i] = max(gap, 0.0) + 0.1
            z[_E, i] = z[_S, i] - gap
            z[_LAM, i] = 0.5 * rho[i]
            z[_MU, i] = 0.5 * rho[i]
            count += 2
        else:
            z[_S, i] = max(gap, 0.1)
            z[_LAM, i] = 1.0
            count += 1
    return count


@_jit
def _residuals(y, ry, k_of, cols, coef, d, rho, z):
    """Add g·λ to the stationarity residual, set rs = s − d + gᵀy − e and re = ρ − λ − μ; return the
    complementarity Σ sλ + eμ and the largest |rs|, |re| (NaN if any is not finite)."""
    gap = res = probe = 0.0
    for i in range(d.shape[0]):
        k, lam = k_of[i], z[_LAM, i]
        a = 0.0
        for v in range(cols.shape[1]):
            a += coef[i, v] * y[k, cols[i, v]]
            ry[k, cols[i, v]] += coef[i, v] * lam
        rs = z[_S, i] - d[i] + a - z[_E, i]
        re = rho[i] - lam - z[_MU, i] if rho[i] > 0 else 0.0
        z[_RS, i], z[_RE, i] = rs, re
        gap += z[_S, i] * lam + z[_E, i] * z[_MU, i]
        res = max(res, abs(rs), abs(re))
        probe += rs + re
    return gap, res + 0.0 * probe  # non-finite if any residual is


@_jit
def _weights(Qt, k_of, cols, coef, rho, z):
    """w = 1/(s/λ + e/μ) and Qt += w g gᵀ."""
    for i in range(rho.shape[0]):
        il = 1.0 / z[_LAM, i]
        im = 1.0 / z[_MU, i] if rho[i] > 0 else 0.0
        w = 1.0 / (z[_S, i] * il + z[_E, i] * im)
        z[_IL, i], z[_IM, i], z[_W, i] = il, im, w
        k = k_of[i]
        for a in range(cols.shape[1]):
            ga = w * coef[i, a]
            for b in range(cols.shape[1]):
                Qt[k, cols[i, a], cols[i, b]] += ga * coef[i, b]


@_jit
def _rhs(corrector, sigma_mu, rt, k_of, cols, coef, z):
    """The complementarity right-hand sides (kept in the Δλ, Δμ rows until ``_steps``), ξ with Δλ = w (gᵀΔy + ξ),
    and rt += g w ξ. The corrector adds Mehrotra's second-order term and centring."""
    for i in range(z.shape[1]):
        rl = z[_S, i] * z[_LAM, i]
        rm = z[_E, i] * z[_MU, i]
        if corrector:
            rl += z[_DS, i] * z[_DL, i] - sigma_mu
            rm += z[_DE, i] * z[_DM, i] - sigma_mu
        xi = z[_RS, i] - rl * z[_IL, i] + (rm + z[_E, i] * z[_RE, i]) * z[_IM, i]
        z[_XI, i], z[_DL, i], z[_DM, i] = xi, rl, rm
        f = z[_W, i] * xi
        for v in range(cols.shape[1]):
            rt[k_of[i], cols[i, v]] += coef[i, v] * f


@_jit
def _steps(amax, dy, k_of, cols, coef, rho, z):
    """Recover (Δs, Δλ, Δe, Δμ) of every constraint from gᵀΔy; return the largest step ≤ amax that keeps s, λ, e, μ
    ≥ 0."""
    for i in range(z.shape[1]):
        g = 0.0
        for v in range(cols.shape[1]):
            g += coef[i, v] * dy[k_of[i], cols[i, v]]
        s, lam, e, mu = z[_S, i], z[_LAM, i], z[_E, i], z[_MU, i]
        dl = z[_W, i] * (g + z[_XI, i])
        ds = (-z[_DL, i] - s * dl) * z[_IL, i]
        if amax * ds < -s:
            amax = -s / ds
        if amax * dl < -lam:
            amax = -lam / dl
        dm = de = 0.0
        if rho[i] > 0:
            dm = z[_RE, i] - dl
            de = (-z[_DM, i] - e * dm) * z[_IM, i]
            if amax * de < -e:
                amax = -e / de
            if amax * dm < -mu:
                amax = -mu / dm
        z[_DL, i], z[_DS, i], z[_DM, i], z[_DE, i] = dl, ds, dm, de
    return amax


@_jit
def _gap(alpha, z):
    total = 0.0
    for i in range(z.shape[1]):
        total += (z[_S, i] + alpha * z[_DS, i]) * (z[_LAM, i] + alpha * z[_DL, i])
        total += (z[_E, i] + alpha * z[_DE, i]) * (z[_MU, i] + alpha * z[_DM, i])
    return total


@_jit
def _update(alpha, z):
    for i in range(z.shape[1]):
        z[_S, i] += alpha * z[_DS, i]
        z[_LAM, i] += alpha * z[_DL, i]
        z[_E, i] += alpha * z[_DE, i]
        z[_MU, i] += alpha * z[_DM, i]


# The terminal cone: rows of ``kc`` (n + 1 columns, u = (τ, cw∘(x_N − cx))): s and z, u, rp = u − s, λ = Wz = W⁻¹s,
# v (λ∘v = the complementarity right-hand side), t, w̄, the step Δs, Δz, Δs̃ = W⁻¹Δs, Δz̃ = WΔz, the affine
# step's Δs̃, Δz̃, and scratch; ``kw`` holds W, W⁻¹ and W⁻² (Nesterov-Todd: W = η W̄, W̄ = [[w̄₀, w̄₁ᵀ], [w̄₁,
# I + w̄₁w̄₁ᵀ/(1 + w̄₀)]], w̄₀² − ‖w̄₁‖² = 1). Steps are taken in the scaled space, where λ sits well inside the cone
# while s and z approach its boundary: the step lengths and Δz then stay accurate to rounding.
_CS, _CZ, _CU, _CRP, _CLAM, _CV, _CT, _CWB, _CDS, _CDZ, _CST, _CZT, _CSA, _CZA, _CTMP = range(15)


@_jit
def _cone_start(y, N, n, cw, cx, kc):
    """s = u at y pushed inside the cone (s₀ = max(u₀, ‖u₁‖) + 1), z = Js / det(s): s∘z = e, a centred start."""
    u, s, z = kc[_CU], kc[_CS], kc[_CZ]
    _cone_u(y, N, n, cw, cx, u)
    norm1 = 0.0
    for j in range(1, n + 1):
        norm1 += u[j] * u[j]
        s[j] = u[j]
    s[0] = max(u[0], np.sqrt(norm1)) + 1.0
    det = s[0] * s[0] - norm1
    for j in range(n + 1):
        z[j] = (s[j] if j == 0 else -s[j]) / det


@_jit
def _cone_u(y, N, n, cw, cx, u):
    """u = (τ, cw∘(x_N − cx)): the terminal cone's point at y."""
    u[0] = y[N, n]
    for a in range(n):
        u[a + 1] = cw[a] * (y[N, a] - cx[a])


@_jit
def _cone_residuals(gap, y, ry, N, n, cw, cx, kc):
    """rp = u − s; add −Fᵀz to the stationarity residual (F: (x_N, τ) → u); return gap + sᵀz and max |rp| (NaN if
    any is not finite)."""
    u, s, z, rp = kc[_CU], kc[_CS], kc[_CZ], kc[_CRP]
    _cone_u(y, N, n, cw, cx, u)
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


@_jit
def _cone_factor(PN, cw, kc, kw, pvec):
    """The scaling at s, z, then τ eliminated from stage N in closed form: PN += D S D with S = η⁻²(I + 2w̄₁w̄₁ᵀ)⁻¹
    the Schur complement of W⁻² (D = diag(cw)), pvec = −D W⁻²₁₀ / W⁻²₀₀; returns 1 / W⁻²₀₀. Forming S from W⁻²
    instead cancels digits of order η⁻²w̄₀² (the failures measured in docs/design.md)."""
    n = cw.shape[0]
    eta = _nt_scaling(kc[_CS], kc[_CZ], kw[0], kw[1], kw[2], kc[_CLAM], kc[_CWB])
    wb = kc[_CWB]
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


@_jit
def _nt_scaling(s, z, W, Wi, Wi2, lam, wbar):
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


@_jit
def _cone_rhs(corrector, sigma_mu, rt, N, n, cw, kc, kw):
    """λ∘(Δs̃ + Δz̃) = r_c with r_c = −λ∘λ (the corrector adds σμe − Δs̃_a∘Δz̃_a): v = λ⁻¹∘r_c (the Jordan
    inverse), t = W⁻¹v − W⁻²rp, and rt −= Fᵀt."""
    m = n + 1
    lam, rc, v, t, a, b = kc[_CLAM], kc[_CTMP], kc[_CV], kc[_CT], kc[_CSA], kc[_CZA]
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
    Wi, Wi2, rp = kw[1], kw[2], kc[_CRP]
    for i in range(m):
        acc = 0.0
        for j in range(m):
            acc += Wi[i, j] * v[j] - Wi2[i, j] * rp[j]
        t[i] = acc
    rt[N, n] -= t[0]
    for i in range(n):
        rt[N, i] -= cw[i] * t[i + 1]


@_jit
def _cone_steps(amax, corrector, dy, rt, N, n, cw, m00inv, pvec, kc, kw):
    """Δτ from Δx_N (the closed-form elimination), Δu = FΔy, Δs = Δu + rp, then in the scaled space Δs̃ = W⁻¹Δs,
    Δz̃ = v − Δs̃ and Δz = W⁻¹Δz̃; returns the largest step ≤ amax that keeps λ + αΔs̃ and λ + αΔz̃ (so s and z) in
    the cone. The affine step keeps its Δs̃, Δz̃ for the corrector."""
    m = n + 1
    u, ds, dz, st, zt, v, rp, Wi = kc[_CU], kc[_CDS], kc[_CDZ], kc[_CST], kc[_CZT], kc[_CV], kc[_CRP], kw[1]
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
    lam = kc[_CLAM]
    amax = _cone_step(lam, st, _cone_step(lam, zt, amax))
    if corrector == 0:
        for j in range(m):
            kc[_CSA, j], kc[_CZA, j] = st[j], zt[j]
    return amax


@_jit
def _cone_gap(total, alpha, kc):
    """total + sᵀz after a step α, from the scaled point: (λ + αΔs̃)ᵀ(λ + αΔz̃)."""
    for j in range(kc.shape[1]):
        total += (kc[_CLAM, j] + alpha * kc[_CST, j]) * (kc[_CLAM, j] + alpha * kc[_CZT, j])
    return total


@_jit
def _cone_step(x, d, amax):
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
