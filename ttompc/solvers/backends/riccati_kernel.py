"""A primal-dual interior-point method for stage-wise QPs (``riccati_qp``: the problem, its options and result) whose
Newton systems are solved by a Riccati recursion, compiled with numba. The whole solve is one call, so Python never
runs inside an iteration.

Eliminating each constraint's slacks and multipliers from the Newton system leaves a weight on gᵀΔy
(``riccati_rows``), so each stage's Hessian gains Σ w g gᵀ and the remaining system (stage Hessians coupled by the
dynamics; stage N's includes QN) is solved by a backward Riccati pass (P_k, K_k) and a forward rollout:
O(N·(NX+NU)³) per iteration instead of a sparse LDLᵀ of the whole KKT matrix. Mehrotra predictor-corrector steps
reuse one factorisation per iteration. The terminal cone (``riccati_cone``) is eliminated from stage N in closed form.

One iteration of ``_ipm``: the residuals (``_stage_residuals``, the constraints', ``_stationarity``), the convergence
test and the best iterate (``_is_best``, ``_stop``), the stage Hessians (``_stage_hessians``, the constraints'
weights, ``_terminal_hessian``, the cone's elimination) and their factorisation (``_riccati_factor``), the
predictor and corrector steps (right-hand sides, ``_backward_pass``, ``_forward_rollout``, step lengths) and the
update (``_update``; the constraints take theirs in the next iteration's residual pass: four passes over each
constraint family per iteration, ``riccati_rows``). The parts are inlined (``jit_inlined``): compiled, one loop.

NX and NU are compile-time constants (``numba.literally``) so the small dense loops unroll; one compilation per
(NX, NU), cached on disk: once per machine (where the cache lives, and the times: docs/design.md).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numba import literally

from ttompc.solvers.backends import riccati_cone as cone
from ttompc.solvers.backends import riccati_rows as family
from ttompc.solvers.backends.riccati_jit import jit, jit_inlined
from ttompc.solvers.backends.riccati_qp import STATE_COLS, DualState, RiccatiOptions, RiccatiResult, StageQPData


@jit
def solve_stage_qp(qp, y, pi, options, zb, zr, NX, NU):
    """Solve ``qp`` (a ``StageQPData``) in place from the primal guess ``y`` (N + 1, NX + NU) and multipliers ``pi``
    (N, NX) of the dynamics, under ``options`` (a ``RiccatiOptions``); ``zb``, ``zr``: the boxes' and rows' state (a
    ``DualState``'s arrays), the start where ``options.warm`` > 0, the last iterate's on return.

    Returns (status, iterations, max residual, duality gap): status 0 converged (residuals ≤ tol, total
    complementarity ≤ gap_tol), 1 iteration limit, 2 numerical breakdown (a non-finite step), 3 stalled or broke
    down within 100× both tolerances (the best iterate is returned: accurate enough for the SCP's 1e-6 merit test)."""
    NX = literally(NX)
    NU = literally(NU)
    return _ipm(qp, y, pi, options, zb, zr, NX, NU)


# a warm start (``RiccatiOptions.warm``) whose largest residual is above this starts cold after its first residual
# pass: such starts stalled (measured, docs/design.md)
WARM_RESIDUAL = 10.0
_ENTRY: dict[tuple[int, int], Callable] = {}  # (NX, NU) -> the compiled specialisation, called directly


def solve(
    qp: StageQPData, y: np.ndarray, pi: np.ndarray, options: RiccatiOptions, state: DualState | None = None
) -> RiccatiResult:
    """``solve_stage_qp`` without numba's literal dispatch, which calling it from Python re-enters every time (as
    costly as the solve; measured in docs/design.md): the first call per (NX, NU) in a process goes through the
    dispatcher (compiling the kernel or loading it from the disk cache), later ones through its entry point.
    ``y`` (N + 1, NX + NU) and ``pi`` (N, NX) are the starting point and receive the solution (y's x_0 and stage N's
    dummy controls are overwritten first); ``state`` the constraints' (``DualState``: where a warm start begins, and
    the last iterate's on return; None: a cold start's own; a ``ValueError`` if it does not fit ``qp``). They and
    ``qp``'s arrays are C-contiguous float64 (int64 indices), which the entry point does not check (``riccati_qp``)."""
    _, n, nu = qp.dynamics.B.shape
    if state is None:
        state = DualState.empty(qp)
    elif state.boxes.shape != (len(qp.boxes.d), STATE_COLS) or state.rows.shape != (len(qp.rows.d), STATE_COLS):
        raise ValueError("riccati kernel: the DualState's arrays do not fit the QP's boxes and rows")
    entry = _ENTRY.get((n, nu))
    if entry is not None:
        return RiccatiResult._make(entry(qp, y, pi, options, state.boxes, state.rows, n, nu))
    from ttompc.progress import status

    status(f"riccati backend: loading its kernel for {n} states and {nu} controls (compiled once per machine, ~20 s)")
    # the first call's types are the entry point's: the options' as documented (the entry point converts numbers)
    options = RiccatiOptions(float(options.tol), float(options.gap_tol), int(options.max_iter), float(options.warm))
    out = solve_stage_qp(qp, y, pi, options, state.boxes, state.rows, n, nu)
    for sig, result in solve_stage_qp.overloads.items():
        if getattr(sig[-2], "literal_value", None) == n and getattr(sig[-1], "literal_value", None) == nu:
            _ENTRY[(n, nu)] = result.entry_point
    return RiccatiResult._make(out)


@jit
def _cold_start(y, bk, bj, bs, bd, brho, zb, rk, ri, rg, rd, rrho, zr):
    """The boxes' (width-1 rows) and the rows' cold start (``family.start``): their complementarity count."""
    n_comp = family.start(y, bk, bj.reshape(-1, 1), bs.reshape(-1, 1), bd, brho, zb)
    return n_comp + family.start(y, rk, ri, rg, rd, rrho, zr)


@jit
def _ipm(qp, y, pi, opt, zb, zr, n, nu):
    """The iterations (the module docstring's); returns what ``solve_stage_qp`` does. The structures' arrays are taken
    out once, here, and the functions below take arrays: numba counts references to arrays taken out of a structure,
    which inside the iterations costs more than a small stage QP's arithmetic."""
    A, B, c, Qd, q, QN = qp.dynamics.A, qp.dynamics.B, qp.dynamics.c, qp.cost.Qd, qp.cost.q, qp.cost.QN
    bk, bj, bs, bd, brho = qp.boxes.k, qp.boxes.j, qp.boxes.sign, qp.boxes.d, qp.boxes.rho
    rk, ri, rg, rd, rrho = qp.rows.k, qp.rows.cols, qp.rows.coef, qp.rows.d, qp.rows.rho
    cw, cx = qp.cone.w, qp.cone.center
    N, ny, has_cone = A.shape[0], n + nu, cw.shape[0] > 0
    # each constraint family's state: zb, zr (riccati_rows); the cone's state, scaling and τ's elimination
    kc, kw, pvec = np.zeros((cone.STATE_ROWS, n + 1)), np.zeros((3, n + 1, n + 1)), np.zeros(n)
    _fixed_entries(qp.dynamics.x0, y, N, n, nu)
    if opt.warm > 0.0:
        n_comp = family.warm_start(y, bk, bj.reshape(-1, 1), bs.reshape(-1, 1), bd, brho, opt.warm, zb)
        n_comp += family.warm_start(y, rk, ri, rg, rd, rrho, opt.warm, zr)
    else:
        n_comp = _cold_start(y, bk, bj, bs, bd, brho, zb, rk, ri, rg, rd, rrho, zr)
    if has_cone:
        cone.start(y, N, n, cw, cx, kc)
        n_comp += 1
    ry, rt, dy = np.zeros((N + 1, ny)), np.zeros((N + 1, ny)), np.zeros((N + 1, ny))  # stationarity, rhs, step
    rdyn, dpi = np.zeros((N, n)), np.zeros((N, n))  # A x + B u + c − x⁺, Δπ
    Qt = np.zeros((N + 1, ny, ny))  # stage Hessians + Σ w g gᵀ
    P, p = np.zeros((N + 1, n, n)), np.zeros((N + 1, n))  # Riccati cost-to-go Hessians and gradients
    S, K, L = np.zeros((N, nu, n)), np.zeros((N, nu, n)), np.zeros((N, nu, nu))  # Q_ux + BᵀP⁺A, gains, chol(R̃)
    PA, PB, Ruu, tmp, tu = np.zeros((n, n)), np.zeros((n, nu)), np.zeros((nu, nu)), np.zeros(n), np.zeros(nu)
    y_best, pi_best = y.copy(), pi.copy()  # the iterate closest to the tolerances, by max(res/tol, gap/gap_tol)
    best = np.array([np.inf, np.inf, np.inf, 0.0])  # its score, residual and gap; iterations since it improved
    terms = np.zeros(2)  # the terms in α and α² of the constraints' complementarity after a step α (``family.steps``)
    res = gap = np.inf
    alpha = 0.0  # the last step, which the constraints take in their next residual pass
    for it in range(opt.max_iter):
        # ------------------------------------------------------------------------------ residuals, convergence
        res, probe = _stage_residuals(A, B, c, Qd, q, QN, y, pi, ry, rdyn, n, nu)
        gap_b, res_b = family.box_residuals(alpha, y, ry, bk, bj, bs, bd, brho, zb)
        gap_r, res_r = family.residuals(alpha, y, ry, rk, ri, rg, rd, rrho, zr)
        gap, res = gap_b + gap_r, max(res, res_b, res_r)
        if has_cone:
            gap, res_c = cone.residuals(gap, y, ry, N, n, cw, cx, kc)
            res = max(res, res_c)
        res = _stationarity(ry, res, probe, has_cone, n, nu)
        if it == 0 and opt.warm > 0.0 and not res <= WARM_RESIDUAL:  # too far from feasible: start cold instead
            n_comp = _cold_start(y, bk, bj, bs, bd, brho, zb, rk, ri, rg, rd, rrho, zr) + (1 if has_cone else 0)
            continue
        mu = gap / max(n_comp, 1)
        if res <= opt.tol and gap <= opt.gap_tol:
            return 0, it, res, gap
        if _is_best(res, gap, opt.tol, opt.gap_tol, best):
            _copy(y, y_best)
            _copy(pi, pi_best)
        stop = _stop(res, gap, best)
        if stop >= 0:
            _copy(y_best, y)
            _copy(pi_best, pi)
            return stop, it, best[1], best[2]
        # ---------------------------------------------------------------- stage Hessians, Riccati factorisation
        _stage_hessians(Qd, Qt, n, nu)
        _copy(ry, rt)  # the predictor's right-hand side, the constraints' terms added with their weights
        family.box_weights(Qt, rt, bk, bj, bs, brho, zb)
        family.weights(Qt, rt, rk, ri, rg, rrho, zr)
        _terminal_hessian(Qt, QN, P, n)
        m00inv = cone.factor(P[N], cw, kc, kw, pvec) if has_cone else 0.0
        _riccati_factor(A, B, Qt, P, S, L, K, PA, PB, Ruu, tu, n, nu)
        # ------------------------------------------------------------- predictor, then corrector step; update
        sigma_mu = 0.0
        for corrector in range(2):
            if corrector:
                _copy(ry, rt)
                family.box_rhs(sigma_mu, rt, bk, bj, bs, zb)
                family.rhs(sigma_mu, rt, rk, ri, rg, zr)
            if has_cone:
                cone.rhs(corrector, sigma_mu, rt, N, n, cw, kc, kw)
            _backward_pass(A, B, P, L, S, p, rt, rdyn, dy, tmp, tu, pvec, has_cone, n, nu)
            _forward_rollout(A, B, K, rdyn, dy, n, nu)
            terms[0] = terms[1] = 0.0
            amax = family.box_steps(1.0, dy, bk, bj, bs, brho, zb, terms)
            amax = family.steps(amax, dy, rk, ri, rg, rrho, zr, terms)
            if has_cone:
                amax = cone.steps(amax, corrector, dy, rt, N, n, cw, m00inv, pvec, kc, kw)
            if corrector == 0:  # Mehrotra's centring from the affine step's complementarity
                gap_aff = max(gap_b + gap_r + amax * (terms[0] + amax * terms[1]), 0.0)
                if has_cone:
                    gap_aff = cone.step_gap(gap_aff, amax, kc)
                sigma_mu = (gap_aff / max(n_comp, 1) / mu) ** 3 * mu
            else:
                alpha = min(1.0, 0.995 * amax)
        _update(alpha, P, p, dy, dpi, y, pi, n)  # the constraints' in their next residual pass
        if has_cone:
            cone.update(alpha, n, kc)
    if best[0] <= 100.0:
        y[:, :] = y_best
        pi[:, :] = pi_best
        return 3, opt.max_iter, best[1], best[2]
    return 1, opt.max_iter, res, gap


@jit_inlined
def _fixed_entries(x0, y, N, n, nu):
    """x_0 and stage N's dummy controls (0) into y."""
    for j in range(n):
        y[0, j] = x0[j]
    for j in range(nu):
        y[N, n + j] = 0.0


@jit_inlined
def _stage_residuals(A, B, c, Qd, q, QN, y, pi, ry, rdyn, n, nu):
    """The stationarity residual of the cost and the dynamics (into ry: the constraints add theirs) and the dynamics
    residual A x + B u + c − x⁺ (into rdyn); returns its largest entry and the sum of its entries."""
    N = A.shape[0]
    for k in range(N + 1):
        for j in range(n + nu):
            ry[k, j] = Qd[k, j] * y[k, j] + q[k, j]
    if QN.shape[0] > 0:
        for a in range(n):
            t = 0.0
            for b in range(n):
                t += QN[a, b] * y[N, b]
            ry[N, a] += t
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
    return res, probe


@jit_inlined
def _stationarity(ry, res, probe, has_cone, n, nu):
    """Zero the entries of ry on fixed variables; returns the largest residual, ``res`` and ry's included (NaN if
    any residual, ``probe`` their partial sum included, is not finite)."""
    N = ry.shape[0] - 1
    for j in range(n):
        ry[0, j] = 0.0  # x_0 is fixed
    for j in range(1 if has_cone else 0, nu):
        ry[N, n + j] = 0.0  # the dummy controls of the last stage (τ is the first where there is a cone)
    for k in range(N + 1):
        for j in range(n + nu):
            res = max(res, abs(ry[k, j]))
            probe += ry[k, j]
    res += 0.0 * probe
    return res


@jit_inlined
def _is_best(res, gap, tol, gap_tol, best):
    """Whether this iterate is the closest to the tolerances so far, by max(res/tol, gap/gap_tol) (False for NaN: a
    breakdown never is); ``best`` (its score, residual and gap, iterations since it improved) updated."""
    score = max(res / tol, gap / gap_tol)
    improved = score < best[0]
    if improved:
        best[0], best[1], best[2], best[3] = score, res, gap, 0.0
    else:
        best[3] += 1.0
    return improved


@jit_inlined
def _stop(res, gap, best):
    """Near the optimum the Newton systems lose accuracy (weights λ/s → 0 or ∞): the residual can stall or grow
    while the gap falls, up to a non-finite step. The status to stop with the best iterate: 3 once it is within 100×
    both tolerances and has not improved for 3 iterations, or on a breakdown (3 within 100×, else 2); −1 to go on."""
    stop = -1
    if not np.isfinite(res + gap) or (best[3] >= 3.0 and best[0] <= 100.0):
        stop = 3 if best[0] <= 100.0 else 2
    return stop


@jit_inlined
def _stage_hessians(Qd, Qt, n, nu):
    """Qt_k = diag(Qd_k) + 1e-10 I (the constraints' weights are added next)."""
    for k in range(Qd.shape[0]):
        for a in range(n + nu):
            for b in range(n + nu):
                Qt[k, a, b] = 0.0
            Qt[k, a, a] = Qd[k, a] + 1e-10


@jit_inlined
def _terminal_hessian(Qt, QN, P, n):
    """P_N = stage N's state block of Qt, plus QN where there is one (the cone's elimination is added next)."""
    N = Qt.shape[0] - 1
    for a in range(n):
        for b in range(n):
            P[N, a, b] = Qt[N, a, b]
    if QN.shape[0] > 0:
        for a in range(n):
            for b in range(n):
                P[N, a, b] += QN[a, b]


@jit_inlined
def _riccati_factor(A, B, Qt, P, S, L, K, PA, PB, Ruu, tu, n, nu):
    """The backward pass from P_N: S_k = Q_ux + BᵀP⁺A, the Cholesky factor L_k of R + BᵀP⁺B, the gains K_k and P_k
    (PA, PB, Ruu, tu: scratch)."""
    for k in range(A.shape[0] - 1, -1, -1):
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
        _chol(Ruu, L, k, nu)
        for b in range(n):  # K = −Ruu⁻¹ S
            for a in range(nu):
                tu[a] = S[k, a, b]
            _cho_solve(L, k, tu, nu)
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


@jit_inlined
def _copy(src, dst):
    """dst ← src (same shape)."""
    for k in range(src.shape[0]):
        for j in range(src.shape[1]):
            dst[k, j] = src[k, j]


@jit_inlined
def _backward_pass(A, B, P, L, S, p, rt, rdyn, dy, tmp, tu, pvec, has_cone, n, nu):
    """The Newton step for the right-hand side rt, backward: the feedforward terms p_k and the controls' parts
    −(R + BᵀP⁺B)⁻¹(r_u + Bᵀ(P⁺ rdyn + p⁺)) of the step (into dy; tmp, tu: scratch)."""
    N = A.shape[0]
    for a in range(n):
        p[N, a] = rt[N, a] + (pvec[a] * rt[N, n] if has_cone else 0.0)
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
        _cho_solve(L, k, tu, nu)
        for a in range(nu):
            dy[k, n + a] = -tu[a]
        for a in range(n):
            t = rt[k, a]
            for e in range(n):
                t += A[k, e, a] * tmp[e]
            for e in range(nu):
                t -= S[k, e, a] * tu[e]
            p[k, a] = t


@jit_inlined
def _forward_rollout(A, B, K, rdyn, dy, n, nu):
    """The Newton step, forward from Δx_0 = 0: Δu_k += K_k Δx_k, Δx_{k+1} = A_k Δx_k + B_k Δu_k + rdyn_k (into dy;
    stage N's Δτ is the cone's, ``riccati_cone.steps``)."""
    for a in range(n):
        dy[0, a] = 0.0
    for k in range(A.shape[0]):
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


@jit_inlined
def _update(alpha, P, p, dy, dpi, y, pi, n):
    """Δπ_k = P_{k+1} Δx_{k+1} + p_{k+1}, then the step α in y and π (the constraints take theirs)."""
    N = pi.shape[0]
    for k in range(N):
        for a in range(n):
            t = p[k + 1, a]
            for b in range(n):
                t += P[k + 1, a, b] * dy[k + 1, b]
            dpi[k, a] = t
    for k in range(N + 1):
        for j in range(y.shape[1]):
            y[k, j] += alpha * dy[k, j]
    for k in range(N):
        for a in range(n):
            pi[k, a] += alpha * dpi[k, a]


@jit
def _chol(M, L, k, m):
    """L_k L_kᵀ = M for an m×m SPD block (a pivot below 1e-14 is clamped: the barrier keeps M positive definite)."""
    for j in range(m):
        s = M[j, j]
        for i in range(j):
            s -= L[k, j, i] * L[k, j, i]
        L[k, j, j] = np.sqrt(max(s, 1e-14))
        for i in range(j + 1, m):
            t = M[i, j]
            for e in range(j):
                t -= L[k, i, e] * L[k, j, e]
            L[k, i, j] = t / L[k, j, j]


@jit
def _cho_solve(L, k, b, m):
    """b ← (L_k L_kᵀ)⁻¹ b in place."""
    for i in range(m):
        t = b[i]
        for e in range(i):
            t -= L[k, i, e] * b[e]
        b[i] = t / L[k, i, i]
    for i in range(m - 1, -1, -1):
        t = b[i]
        for e in range(i + 1, m):
            t -= L[k, e, i] * b[e]
        b[i] = t / L[k, i, i]
