"""The checks of a scenario's dynamics in every form it has (``ttompc.scenario_check``), each against the one source,
``Scenario.step``: the affine model (``convex_model``) and its Jacobians (``jacobian``, by central finite
differences), the rollout's torch model (``batched_model``) and the fused decoder's compiled step (``fused_step``),
on random states of sampled problems."""

from __future__ import annotations

import ctypes
from collections.abc import Callable

import numpy as np

from ttompc.scenario_check_base import MODEL_TOL, CheckContext, fail, probe_states, worst
from ttompc.scenarios.base import ConvexModel, Problem, Window

JACOBIAN_TOL = 1e-4  # scaled units: central differences are accurate to ~1e-7 at these step sizes
FUSED_TOL = 1e-5  # relative: the fused step runs in float32


def _model_error(
    ctx: CheckContext, p: Problem, w: Window, model: ConvexModel, X: np.ndarray, U: np.ndarray
) -> np.ndarray:
    """|A x + B u + c − step(x, u)| per window step and state (H, n), in units of ``state_scale``."""
    pred = np.einsum("jab,jb->ja", model.A, X[:-1]) + np.einsum("jab,jb->ja", model.B, U) + model.c
    return np.abs(pred - ctx.sc.step_window(p, w.start, X[:-1], U)) / ctx.sx


def convex_model(ctx: CheckContext) -> str:
    sc = ctx.sc
    n, m = sc.state_dim, sc.control_dim
    exact_rows = np.setdiff1d(np.arange(n), sc.approximate_rows) if sc.approximate_rows else np.arange(0)
    for s, p in ctx.problems():
        X_all, U_all = ctx.reference(p)
        for w in ctx.windows(p):
            H = w.length
            X, U = X_all[w.start : w.stop + 1], U_all[w.start : w.stop]
            model = sc.convex_model(p, w, X, U)
            if model.A.shape != (H, n, n) or model.B.shape != (H, n, m) or model.c.shape != (H, n):
                fail(
                    f"window {w.start}+{H}: A {model.A.shape}, B {model.B.shape}, c {model.c.shape}, expected "
                    f"({H}, {n}, {n}), ({H}, {n}, {m}), ({H}, {n})"
                )
            for label, M, mask in (("A", model.A, model.A_mask), ("B", model.B, model.B_mask)):
                if mask is not None and np.any(M[:, ~np.asarray(mask, bool)] != 0):
                    (j, r, c), _ = worst(np.abs(M * ~np.asarray(mask, bool)))
                    fail(f"{label}[{j}][{r}, {c}] is nonzero outside {label}_mask (window {w.start}+{H})")
            (j, i), err = worst(_model_error(ctx, p, w, model, X, U))
            if err > MODEL_TOL:
                fail(
                    f"A x + B u + c differs from step() at the reference it was built on: step {w.start + j}, "
                    f"state {i}, {err:.2e} in units of state_scale (problem seed {s})"
                )
            Xp = X + ctx.rng.normal(size=X.shape) * ctx.sx * 0.1
            Up = U + ctx.rng.normal(size=U.shape) * ctx.su * 0.1
            away = _model_error(ctx, p, w, model, Xp, Up)
            rows, what = (
                (np.arange(n), "exact_linear_dynamics is set")
                if sc.exact_linear_dynamics
                else (exact_rows, "it is not in approximate_rows")
            )
            if len(rows) and away[:, rows].max() > MODEL_TOL:
                (j, i), err = worst(away[:, rows])
                fail(
                    f"state row {rows[i]} of the affine model is not exact away from the reference ({err:.2e} "
                    f"at step {w.start + j}) but {what} (problem seed {s})"
                )
    return "A x + B u + c reproduces step() at the reference" + (
        "" if not sc.exact_linear_dynamics else ", and everywhere (exact linear dynamics)"
    )


def jacobian(ctx: CheckContext) -> str:
    sc = ctx.sc
    n, m = sc.state_dim, sc.control_dim
    for s, p in ctx.problems():
        X, U = ctx.reference(p)
        w = Window.full(p)
        model = sc.convex_model(p, w, X, U)
        for j in sorted({0, p.n_steps // 2, p.n_steps - 1}):
            x, u = X[j], U[j]
            hx, hu = 1e-6 * np.maximum(ctx.sx, np.abs(x)), 1e-6 * np.maximum(ctx.su, np.abs(u))
            Jx = np.stack(
                [
                    (sc.step(p, j, x + hx[i] * e, u) - sc.step(p, j, x - hx[i] * e, u)) / (2 * hx[i])
                    for i, e in enumerate(np.eye(n))
                ],
                axis=1,
            )
            Ju = np.stack(
                [
                    (sc.step(p, j, x, u + hu[i] * e) - sc.step(p, j, x, u - hu[i] * e)) / (2 * hu[i])
                    for i, e in enumerate(np.eye(m))
                ],
                axis=1,
            )
            for label, got, fd, col in (("A", model.A[j], Jx, ctx.sx), ("B", model.B[j], Ju, ctx.su)):
                err = np.abs(got - fd) * col[None, :] / ctx.sx[:, None]  # in units of the scales
                (r, c), largest = worst(err)
                if largest > JACOBIAN_TOL:
                    fail(
                        f"{label}[{r}, {c}] at step {j} is {got[r, c]:.6g} but finite differences of step() "
                        f"give {fd[r, c]:.6g} (problem seed {s})"
                    )
    return "A and B match central finite differences of step()"


def batched_model(ctx: CheckContext) -> str:
    import torch

    sc = ctx.sc
    pairs = ctx.problems()
    model = sc.batched_model([p for _, p in pairs])

    def torch_step(S: np.ndarray, U: np.ndarray, k: int) -> np.ndarray:
        got = model.step(torch.as_tensor(S), torch.as_tensor(U), k)
        if tuple(got.shape) != S.shape or got.dtype != torch.float64:
            fail(f"step(S, A, {k}) returned {tuple(got.shape)} {got.dtype} for float64 states {S.shape}")
        return got.numpy()

    _check_steps(ctx, pairs, "the torch model's step()", torch_step, MODEL_TOL)
    for s, p in pairs:
        X = probe_states(ctx, p)
        states = torch.as_tensor(sc.to_model_states(p, X))
        counts = np.asarray(sc.violations(p, X))
        alone = sc.batched_model([p])  # the problem's own count
        for k in range(len(X)):
            got_count = float(alone.violations(states[k : k + 1], k)[0])
            if got_count != counts[k]:
                fail(
                    f"violations(S, {k}) counts {got_count:g} but the scenario's violations() {counts[k]} "
                    f"(problem seed {s})"
                )
    return "torch step and violation counts match step() and violations()"


def fused_step(ctx: CheckContext) -> str:
    sc = ctx.sc
    pairs = ctx.problems()
    problems = [p for _, p in pairs]
    make = getattr(sc.batched_model(problems), "fused_step", None)
    if not callable(make):
        return "no fused_step: the fused decoder runs the torch decode (declare dynamics = CompiledStep(...))"
    step, params = make()
    if params.shape[0] != len(problems) or params.dtype != np.float32 or not params.flags.c_contiguous:
        shape = f"{params.dtype} {params.shape}"
        fail(f"fused_step() params must be C-contiguous float32 ({len(problems)}, P), got {shape}")
    ptr = ctypes.POINTER(ctypes.c_float)

    def compiled_step(S: np.ndarray, U: np.ndarray, k: int) -> np.ndarray:
        S, U, got = S.astype(np.float32), U.astype(np.float32), np.full(S.shape, np.nan, np.float32)
        for b in range(len(S)):
            x, u, p, out = (a.ctypes.data_as(ptr) for a in (S[b], U[b], params[b], got[b]))
            step.ctypes(x, u, k, p, out)
        return got

    _check_steps(ctx, pairs, "the fused step", compiled_step, FUSED_TOL)
    return "the fused decoder's compiled step matches step() (float32)"


def _transitions(ctx: CheckContext, problems: list[Problem], k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One random transition at step k per problem, in the model representation: states (B, n), controls (B, m) and
    the states ``step`` leads to (B, n)."""
    sc = ctx.sc
    X = np.stack([ctx.reference(p)[0][k] for p in problems])
    U = ctx.controls(len(problems))
    S = np.stack([sc.to_model_states(p, x[None], start=k)[0] for p, x in zip(problems, X, strict=True)])
    nxt = [sc.step(p, k, x, u)[None] for p, x, u in zip(problems, X, U, strict=True)]
    return S, U, np.stack([sc.to_model_states(p, y, start=k + 1)[0] for p, y in zip(problems, nxt, strict=True)])


def _check_steps(
    ctx: CheckContext,
    pairs: list[tuple[int, Problem]],
    what: str,
    step: Callable[[np.ndarray, np.ndarray, int], np.ndarray],
    tol: float,
) -> None:
    """Compare a form's ``step(S, U, k)`` (model states (B, n), controls (B, m) -> next model states (B, n)) with the
    scenario's ``step`` on one random transition per problem (``_transitions``) at the first, middle and last step;
    fail naming the worst entry where they differ by more than ``tol``, relative to each state's largest magnitude
    over the batch (plus one)."""
    problems = [p for _, p in pairs]
    N = problems[0].n_steps
    for k in sorted({0, N // 2, N - 1}):
        S, U, expected = _transitions(ctx, problems, k)
        got = step(S, U, k)
        (b, i), err = worst(np.abs(got - expected) / (np.abs(expected).max(axis=0) + 1.0))
        if not err <= tol:
            where = f"{what} at step {k}, state {i} gives {got[b, i]:.6g}"
            fail(f"{where} but the scenario's step gives {expected[b, i]:.6g} (problem seed {pairs[b][0]})")
