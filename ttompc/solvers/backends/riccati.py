"""The penalised SCP subproblem in stage-wise form (``StageQP``: a ``riccati_qp.StageQPData`` per iteration), solved by
a Riccati interior-point method (``riccati_kernel``, numba): the first solver of the default chain
(``backend="auto"``) wherever the subproblem is a penalised QP, or one whose only cone is an MPC window's soft
terminal term.

It poses the optimisation problem of ``qp.QPSubproblem`` stage by stage instead of as one sparse QP, in the same
non-dimensionalised variables (x/state_scale, u/control_scale), so the two backends reach the same optima:

* stage k holds y_k = [x_k, u_k, ν_k] (ν: virtual control on ``spec.vc_rows``, a column of B equal to 1);
* the L1 fuel cost, the virtual control and the penalised terminal condition are soft boxes with zero width
  (ρ·|v| = ρ·dist(v, [0, 0])), the quadratic cost a diagonal stage Hessian;
* an MPC window's soft terminal term ‖W(x_H − x̄)‖₂ is the kernel's one second-order cone, on the last stage's
  first dummy control τ (its epigraph, at cost τ);
* the ∞-norm trust region and rows on one variable are boxes, other rows sparse over their structural columns
  (normalised, with the penalty scaled so that it still reads in the row's own units); a two-sided row is two
  one-sided rows, each with its own slack, as the QP's e⁺/e⁻ pair; penalised equality rows are two-sided with
  lower = upper;
* x_0 is fixed, so rows on x_0 alone are constants and dropped;
* a quadratic model of a terminal cost-to-go (``SubproblemData.terminal_cost``) is the kernel's dense block QN on
  x_H with its linear term in the last stage's q.

Where the kernel does not converge the same data goes to ``fallback`` (the PIQP chain; for a window, QOCO then
Clarabel, which read a terminal cost-to-go model too), so the backend never returns less than the chain behind it
would.
"""

from __future__ import annotations

import dataclasses
import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from ttompc.scenarios.base import BlockKind
from ttompc.solvers.backends.base import BackendSolution, Fallback, SubproblemSolver, is_qp
from ttompc.solvers.backends.riccati_qp import (
    Boxes,
    DualState,
    Dynamics,
    RiccatiOptions,
    Rows,
    StageCost,
    StageQPData,
    TerminalCone,
)
from ttompc.solvers.spec import QuadraticTerminalCost, SubproblemData, SubproblemSpec, structural_mask

TOL = 1e-8  # residuals of the scaled problem (PIQP's eps_abs)
GAP_TOL = 1e-9  # total complementarity = duality gap: the SCP's stopping rule compares merits to 1e-6
MAX_ITER = 100
# the kernel's warm start between a solve's subproblems (``RiccatiOptions.warm``): its centring δ; 0 starts every
# subproblem cold (measured, iterations per subproblem cold vs warm: docs/benchmarks.md)
WARM = 1e-4


def supports(spec: SubproblemSpec) -> bool:
    """The stage-wise form needs soft (penalised) equalities and terminal condition: the kernel has no equality
    rows besides the dynamics. Its one cone is an MPC window's soft terminal term ‖W(x_H − x̄)‖₂."""
    if not spec.penalized:
        return False
    soft_end = spec.end_form in ("soft", "value")  # the 2-norm term's cone, or a cost-to-go model alone
    return is_qp(spec) or (soft_end and is_qp(dataclasses.replace(spec, end_form="hard")))


@dataclass
class _BlockMap:
    """Where one scenario block's rows go: rows touching one variable become boxes, the rest sparse rows."""

    is_eq: bool
    two_sided: bool
    rho: float  # exact-penalty weight (0: hard)
    steps: np.ndarray  # (K,)
    live: np.ndarray  # (K, M) rows kept (not on x_0 alone)
    single: np.ndarray  # (M,) rows with one structural nonzero (a box on column cols[:, 0])
    mask: np.ndarray  # (M, n + m) structural nonzeros
    cols: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.int64))  # (M, width) structural columns first
    valid: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), bool))  # (M, width) real (not padding)


class StageQP:
    """Index maps from ``SubproblemData`` to the kernel's problem for one structure (see the module docstring)."""

    def __init__(self, spec: SubproblemSpec) -> None:
        if not supports(spec):
            raise ValueError(
                "the riccati backend solves penalised subproblems (formulation 'penalized') that are QPs or whose "
                "only cone is an MPC window's soft terminal term; use backend='auto'"
            )
        self.spec = spec
        H, n, m = spec.H, spec.n, spec.m
        self.sx, self.su = spec.units()
        self.vr = spec.virtual_rows() if spec.virtual_control else np.zeros(0, np.int64)
        self.nu = m + len(self.vr)
        ny = n + self.nu
        self.a_scale = self.sx[None, :] / self.sx[:, None]  # A in scaled variables: diag(1/sx) A diag(sx)
        self.b_scale = self.su[None, :] / self.sx[:, None]
        self.B = np.zeros((H, n, self.nu))
        self.B[:, self.vr, m + np.arange(len(self.vr))] = 1.0
        self.Qd = np.zeros((H + 1, ny))
        self.Qd[H, n:] = 1.0  # the last stage's dummy controls
        self.cone = spec.end_form == "soft"  # τ ≥ ‖W(x_H − x̄)‖₂ at cost τ, τ the last stage's first dummy control
        if self.cone:
            self.Qd[H, n] = 0.0
        if spec.cost_norm == "quad":
            self.Qd[:H, n : n + m] = spec.fuel_weight * self.su**2
        self.q = np.zeros((H + 1, ny))
        if self.cone:
            self.q[H, n] = 1.0
        # constant soft zero boxes: the L1 fuel cost and the virtual control
        ks, js, rho = [], [], []
        if spec.cost_norm == "l1":
            ks.append(np.repeat(np.arange(H), m))
            js.append(np.tile(n + np.arange(m), H))
            rho.append(np.tile(spec.fuel_weight * self.su, H))
        if len(self.vr):
            ks.append(np.repeat(np.arange(H), len(self.vr)))
            js.append(np.tile(n + m + np.arange(len(self.vr)), H))
            rho.append(np.tile(spec.penalty * self.sx[self.vr], H))
        k0 = np.concatenate(ks) if ks else np.zeros(0, np.int64)
        j0 = np.concatenate(js) if js else np.zeros(0, np.int64)
        r0 = np.concatenate(rho) if rho else np.zeros(0)
        self.n_zero = 2 * len(k0)
        # boxes whose places are fixed: zero boxes (±v ≤ 0), the terminal condition (±x_H ≤ ±goal), the trust
        # region (±x_k ≤ ±x̄_k + δ, hard); only their right-hand sides change (``arrays``)
        self.tr_steps = np.asarray(spec.tr_states if spec.trust == "linf" else (), dtype=np.int64)
        T = len(self.tr_steps)
        both = np.array([1.0, -1.0])
        self._box_k = np.concatenate([np.tile(k0, 2), np.full(2 * n, H), np.repeat(np.tile(self.tr_steps, 2), n)])
        self._box_j = np.concatenate([np.tile(j0, 2), np.tile(np.arange(n), 2), np.tile(np.arange(n), 2 * T)])
        self._box_s = np.concatenate([np.repeat(both, len(k0)), np.repeat(both, n), np.repeat(both, T * n)])
        self._box_rho = np.concatenate([np.tile(r0, 2), np.tile(spec.penalty * self.sx, 2), np.zeros(2 * T * n)])
        self.blocks = [self._block_map(sig) for sig in spec.blocks]
        # general rows are stored sparse: the structural columns of each row, padded to the widest row
        self.width = max([1] + [int(b.mask.sum(axis=1).max()) for b in self.blocks if len(b.mask)])
        for b in self.blocks:
            order = np.argsort(~b.mask, axis=1, kind="stable")[:, : self.width]  # structural columns first
            b.cols = np.ascontiguousarray(order)  # the compiled build takes C-contiguous arrays
            b.valid = np.take_along_axis(b.mask, order, axis=1)

    def _block_map(self, sig: tuple) -> _BlockMap:
        spec, n, m = self.spec, self.spec.n, self.spec.m
        name, kind, steps, M, has_u, soft, _, two_sided, gx_mask, gu_mask = sig
        steps = np.asarray(steps, dtype=np.int64)
        if has_u and len(steps) and steps.max() >= spec.H:
            raise ValueError(f"block {name!r} puts control rows on step {steps.max()} >= window length {spec.H}")
        mask = np.hstack(
            [structural_mask(gx_mask, (M, n)), structural_mask(gu_mask, (M, m)) if has_u else np.zeros((M, m), bool)]
        )
        is_eq = BlockKind(kind) is BlockKind.EQ
        live = np.ones((len(steps), M), bool)
        live[steps == 0] = mask[:, n:].any(axis=1)  # rows on x_0 alone are constants (x_0 is fixed): dropped
        return _BlockMap(
            is_eq=is_eq,
            two_sided=bool(two_sided) or is_eq,
            rho=spec.penalty if (spec.penalized and (soft or is_eq)) else 0.0,
            steps=steps,
            live=live,
            single=mask.sum(axis=1) == 1,
            mask=mask,
        )

    def build(self, data: SubproblemData, compiled: bool = True) -> StageQPData:
        """The kernel's problem for one iteration's data, in the scaled variables; the scenario blocks' constraints
        by the compiled path (``riccati_build.constraints``) or, ``compiled=False``, the NumPy reference
        (``_constraints``): the same arrays."""
        n, m, sx = self.spec.n, self.spec.m, self.sx
        A = np.ascontiguousarray(data.model.A * self.a_scale)
        B = self.B.copy()
        B[:, :, :m] = data.model.B * self.b_scale
        c = data.model.c / sx
        # the terminal condition's boxes (none for the soft terminal term: its cone)
        goal = data.goal / sx if self.spec.end_form == "hard" else np.full(n, np.inf)
        ref = data.X_ref[self.tr_steps] / sx  # (T, n); an infinite δ gives infinite bounds, dropped below
        half = data.delta / sx
        d = np.concatenate([np.zeros(self.n_zero), goal, -goal, (ref + half).ravel(), (half - ref).ravel()])
        if compiled:
            from ttompc.solvers.backends.riccati_build import constraints  # numba: imported at the first solve

            boxes, rows = constraints(self, data, d)
        else:
            boxes, rows = self._constraints(data, d)
        if self.cone:
            assert data.terminal_weights is not None and data.terminal_target is not None
            cone = TerminalCone(np.asarray(data.terminal_weights * sx, np.float64), data.terminal_target / sx)
        else:
            cone = TerminalCone.none()
        cost = StageCost(self.Qd, self.q)
        if data.terminal_cost is not None:
            QN, grad = self._terminal_block(data.terminal_cost)
            q = self.q.copy()
            q[-1, :n] += grad
            cost = StageCost(self.Qd, q, QN)
        return StageQPData(
            dynamics=Dynamics(A, B, c, data.x_start / sx),
            cost=cost,
            boxes=boxes,
            rows=rows,
            cone=cone,
        )

    def _constraints(self, data: SubproblemData, d: np.ndarray) -> tuple[Boxes, Rows]:
        """The reference form of ``riccati_build.constraints``: the fixed boxes (right-hand sides ``d``), then each
        scenario block's rows on one variable as boxes and its other rows as sparse rows; bounds not finite dropped."""
        n, m, sx, su = self.spec.n, self.spec.m, self.sx, self.su
        boxes = [(self._box_k, self._box_j, self._box_s, d, self._box_rho)]
        rows = []
        for b, block in zip(self.blocks, data.blocks, strict=True):
            K, M = block.h.shape
            G = np.zeros((K, M, n + m))
            G[:, :, :n] = block.Gx * sx
            if block.Gu is not None:
                G[:, :, n:] = block.Gu * su
            upper = block.h
            lower = block.h if b.is_eq or block.lower is None else block.lower  # (used where two-sided)
            kk = np.broadcast_to(b.steps[:, None], (K, M))
            # boxes: the row's one variable, scaled by its coefficient g (sign and size may change per iteration)
            sel = b.live & b.single[None, :]
            if sel.any():
                col = b.cols[:, 0]  # a box row's one variable
                g = np.take_along_axis(G, np.broadcast_to(col[None, :, None], (K, M, 1)), axis=2)[..., 0][sel]
                ok = g != 0.0
                g, ag = g[ok], np.abs(g[ok])
                kb, jb = kk[sel][ok], np.broadcast_to(col[None, :], (K, M))[sel][ok]
                boxes.append((kb, jb, np.sign(g), upper[sel][ok] / ag, b.rho * ag))
                if b.two_sided:
                    boxes.append((kb, jb, -np.sign(g), -lower[sel][ok] / ag, b.rho * ag))
            sel = b.live & ~b.single[None, :]
            if sel.any():
                g = np.take_along_axis(G, np.broadcast_to(b.cols[None], (K, M, self.width)), axis=2)
                g = (g * b.valid[None])[sel]  # (R, width)
                cols = np.broadcast_to(b.cols[None], (K, M, self.width))[sel]
                norm = np.linalg.norm(g, axis=1)
                norm[norm == 0.0] = 1.0
                g /= norm[:, None]
                rows.append((kk[sel], cols, g, upper[sel] / norm, b.rho * norm))
                if b.two_sided:
                    rows.append((kk[sel], cols, -g, -lower[sel] / norm, b.rho * norm))
        bk, bj, bs, bd, brho = (np.concatenate(parts) for parts in zip(*boxes, strict=True))
        keep = np.isfinite(bd)
        bk, bj, bs, bd, brho = bk[keep].astype(np.int64), bj[keep].astype(np.int64), bs[keep], bd[keep], brho[keep]
        if rows:
            rk, ri, rg, rd, rrho = (np.concatenate(parts) for parts in zip(*rows, strict=True))
            keep = np.isfinite(rd)
            rk, ri, rg, rd, rrho = (
                rk[keep].astype(np.int64),
                np.ascontiguousarray(ri[keep], dtype=np.int64),
                np.ascontiguousarray(rg[keep]),
                rd[keep],
                rrho[keep],
            )
        else:
            rk, ri, rg = np.zeros(0, np.int64), np.zeros((0, self.width), np.int64), np.zeros((0, self.width))
            rd, rrho = np.zeros(0), np.zeros(0)
        return Boxes(bk, bj, bs, bd, brho), Rows(rk, ri, rg, rd, rrho)

    def _terminal_block(self, terminal: QuadraticTerminalCost) -> tuple[np.ndarray, np.ndarray]:
        """½ (x − x̄)ᵀP(x − x̄) + gᵀ(x − x̄) in the scaled state x̃ = x / sx: ½ x̃ᵀ QN x̃ + lᵀx̃ + const with QN = SPS
        (symmetrised) and l = S(g − P x̄), S = diag(sx); returns (QN (n, n), l (n,))."""
        P = np.asarray(terminal.hessian, np.float64)
        P = 0.5 * (P + P.T)
        QN = np.ascontiguousarray(self.sx[:, None] * P * self.sx[None, :])
        return QN, self.sx * (terminal.gradient - P @ terminal.center)

    def objective(self, y: np.ndarray, qp: StageQPData, data: SubproblemData, compiled: bool = True) -> float:
        """The subproblem's objective at y (the QP's, up to the constant penalties of rows on x_0 alone), with the
        terminal term's value in place of its epigraph variable τ and the terminal cost-to-go model's constant; the
        QP's by the compiled path (``riccati_build.objective``) or, ``compiled=False``, ``StageQPData.objective``."""
        if compiled:
            from ttompc.solvers.backends.riccati_build import objective

            value = objective(qp, y)
        else:
            value = qp.objective(y)
        if self.cone:
            n = self.spec.n
            value += float(np.linalg.norm(qp.cone.w * (y[-1, :n] - qp.cone.center))) - float(y[-1, n])
        if data.terminal_cost is not None:
            tc = data.terminal_cost
            value += 0.5 * float(tc.center @ tc.hessian @ tc.center) - float(tc.gradient @ tc.center)
        return value


class RiccatiSolver:
    """``StageQP`` + the compiled kernel; a solve that does not converge goes to ``fallback`` (if given).

    ``compiled`` (a class setting, default True): the per-iteration Python around the kernel (the scenario blocks'
    constraints, the objective) runs compiled (``riccati_build``); False runs the NumPy reference, which the tests
    and ``bench/solver_speed.py --only engine`` compare it against (the same stage QPs, iterates and statuses).

    ``warm`` (a class setting, default ``WARM``): after a converged subproblem the next one (an SCP iteration of the
    same solve: ``restart`` ends it) starts from its solution, dynamics multipliers and the constraints' slacks and
    multipliers (``riccati_rows.warm_start`` with centring δ = ``warm``) where its constraints are the same boxes and
    rows; 0, or otherwise, from the reference's states with u = 0, π = 0 and a cold start. The same optimal cost,
    not always the same optimal point: where the optimum is a face (the free-flyer's L1 fuel) a warm start stays
    near the previous solution's point of it, a cold one nears its centre. MPC windows (an end other than "hard")
    start cold: warm, lone and batched episodes part further on such faces (``tests/test_mpc.py``)."""

    name = "riccati"
    compiled: ClassVar[bool] = True
    warm: ClassVar[float] = WARM

    def __init__(self, spec: SubproblemSpec, fallback: Callable[[], SubproblemSolver] | None = None) -> None:
        self.stage = StageQP(spec)
        self.fallback = Fallback(fallback)
        self._last: tuple[np.ndarray, np.ndarray, StageQPData, DualState] | None = None  # y, π, QP, state
        self._warm = spec.end_form == "hard"  # (the class docstring's)

    def restart(self) -> None:
        """The next subproblem starts cold (``warm``); the fallback restarts."""
        self._last = None
        self.fallback.restart()

    def _start(self, qp: StageQPData, data: SubproblemData) -> tuple[np.ndarray, np.ndarray, DualState, float]:
        """The kernel's y, π, constraint state and warm-start δ (0: cold) for ``qp`` (the class docstring's); y's
        states are the reference's either way."""
        st, spec, last = self.stage, self.stage.spec, self._last
        self._last = None
        if last is not None and _same_constraints(last[2], qp):
            y, pi, _, state = last
            delta = self.warm
        else:
            y, pi = np.zeros((spec.H + 1, spec.n + st.nu)), np.zeros((spec.H, spec.n))
            state, delta = DualState.empty(qp), 0.0
        y[:, : spec.n] = data.X_ref / st.sx
        return y, pi, state, delta

    def solve(self, data: SubproblemData) -> tuple[np.ndarray | None, np.ndarray | None, BackendSolution]:
        t0 = time.perf_counter()
        st, spec = self.stage, self.stage.spec
        qp = st.build(data, self.compiled)
        y, pi, state, delta = self._start(qp, data)
        # numba is imported at the first solve, not with the engine (processes that never solve do not pay it)
        from ttompc.solvers.backends.riccati_kernel import solve

        out = solve(qp, y, pi, RiccatiOptions(TOL, GAP_TOL, MAX_ITER, delta), state)
        if out.status == 0 and self.warm > 0.0 and self._warm:  # (status 3's state is not the returned iterate's)
            self._last = (y, pi, qp, state)
        name = ("RICCATI_SOLVED", "RICCATI_MAX_ITER", "RICCATI_NUMERICAL", "RICCATI_SOLVED_INACCURATE")[out.status]
        # the format ``status_iterations`` reads
        status = f"{name} ({out.iterations} it, residual {out.residual:.1e}, gap {out.gap:.1e})"
        ok = out.status in (0, 3)
        sol = BackendSolution(
            None,
            st.objective(y, qp, data, self.compiled) if ok else np.nan,
            ok,
            False,
            status,
            time.perf_counter() - t0,
        )
        if ok:
            sol.costates = pi / st.sx  # multipliers of the scaled dynamics rows x̃_{k+1} = ...: per unit of x_{k+1}
            return y[:, : spec.n] * st.sx, y[: spec.H, spec.n : spec.n + spec.m] * st.su, sol
        return self.fallback.take(data, sol)


def _same_constraints(a: StageQPData, b: StageQPData) -> bool:
    """Whether ``a`` and ``b`` have the same boxes and rows (places and signs; their data may differ), in order."""
    return (
        np.array_equal(a.boxes.k, b.boxes.k)
        and np.array_equal(a.boxes.j, b.boxes.j)
        and np.array_equal(a.boxes.sign, b.boxes.sign)
        and np.array_equal(a.rows.k, b.rows.k)
        and np.array_equal(a.rows.cols, b.rows.cols)
    )


def status_iterations(status: str) -> int | None:
    """The interior-point iterations a kernel solve's status records (``RiccatiSolver.solve``: "NAME (k it, ...)");
    None for a status that records none (another backend's)."""
    m = re.search(r"\((\d+) it", status)
    return None if m is None else int(m.group(1))
