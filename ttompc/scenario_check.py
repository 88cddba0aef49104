"""``check_scenario``: the contract of ``Scenario`` (docs/scenarios.md) checked on sampled problems, each failure
named in one line, so that a new scenario's mistakes surface before a dataset or a model is built on them (the
command: ``ttompc check-scenario``). It sits beside ``ttompc.scenarios``, not in it: the ``solve`` check runs
``ttompc.solvers``, which is built on the scenarios.

The checks are what the engine, the datasets, the rollout and MPC rely on without checking:

* ``interface``: class attributes (dimensions, cost norm, settings, labels, scales) have the documented shapes;
* ``sample``: seeded sampling is reproducible, problems have the declared shapes and pass ``validate``;
* ``features``: ``problem_from_features`` rebuilds a problem from what datasets store, and the representation maps
  invert each other;
* ``convex_model``: at a dynamically consistent reference the affine model reproduces ``step`` (exactly linear
  rows, and every row when ``exact_linear_dynamics``, also away from it), within the declared sparsity masks;
* ``jacobian``: A and B are the derivatives of ``step`` (central finite differences);
* ``batched_model``: the torch model steps like ``step`` and counts violations like ``violations``;
* ``constraints``: block shapes and steps do not depend on the reference, values are finite and within the masks,
  keep-out blocks are non-convex and skip the fixed state 0;
* ``violations``: every state counted as violating is seen by ``path_violation`` (beyond ``scp.feas_tol``) and by
  the linearised keep-out rows at that state;
* ``solve``: sampled problems are solved by REL then SCP, and the SCP solution reaches the goal with no violation.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, NoReturn, get_args

import numpy as np

from ttompc.scenarios.base import (
    BlockKind,
    ConstraintBlock,
    ConvexModel,
    CostNorm,
    InfeasibleProblemError,
    MPCWeights,
    Problem,
    Scenario,
    SCPSettings,
    Window,
)
from ttompc.seeding import problem_seed
from ttompc.solvers.scp import solve_problem

CHECKS = (
    "interface",
    "sample",
    "features",
    "convex_model",
    "jacobian",
    "batched_model",
    "constraints",
    "violations",
    "solve",
)
MODEL_TOL = 1e-8  # relative, in units of the scenario's scales: affine model and torch model against ``step``
JACOBIAN_TOL = 1e-4  # scaled units: central differences are accurate to ~1e-7 at these step sizes


class CheckFailure(Exception):
    """One failed check; the message is the one line shown to the user."""


@dataclass
class Finding:
    """The outcome of one check, printed as one line (``ok`` or ``FAIL``, the check, what was found)."""

    check: str
    ok: bool
    message: str

    def __str__(self) -> str:
        return f"{'ok  ' if self.ok else 'FAIL'}  {self.check}: {self.message}"


def check_scenario(scenario: Scenario, *, problems: int = 3, seed: int = 0, backend: str = "auto") -> Iterator[Finding]:
    """Run every check on ``problems`` sampled problems (problem i from ``problem_seed(seed, i)``, as ``ttompc
    generate`` draws them), yielding each finding as it is made. A check that raises is a failure naming the
    exception; later checks still run, except after a failed ``interface`` check (nothing else is meaningful)."""
    ctx = _Context(scenario, max(problems, 1), seed, backend)
    for name in CHECKS:
        try:
            finding = Finding(name, True, _CHECKS[name](ctx))
        except CheckFailure as err:
            finding = Finding(name, False, str(err))
        except Exception as err:  # the scenario's own code failed: name it, keep checking the rest
            first = str(err).strip().splitlines()[0] if str(err).strip() else ""
            finding = Finding(name, False, f"raised {type(err).__name__}: {first}")
        yield finding
        if name == "interface" and not finding.ok:
            return


class _Context:
    """Sampled problems, scales and references shared by the checks (each built on first use)."""

    def __init__(self, sc: Scenario, problems: int, seed: int, backend: str) -> None:
        self.sc, self.n_problems, self.seed, self.backend = sc, problems, seed, backend
        self.sx, self.su = sc.state_units(), sc.control_units()
        self.rng = np.random.default_rng(seed)
        self._problems: list[tuple[int, Problem]] | None = None

    def problems(self) -> list[tuple[int, Problem]]:
        """(seed, problem) of the first ``n_problems`` sampled problems that pass ``validate``."""
        if self._problems is None:
            out: list[tuple[int, Problem]] = []
            i = 0
            while len(out) < self.n_problems and i < 20 * self.n_problems:
                s = problem_seed(self.seed, i)
                p = self.sc.sample(np.random.default_rng(s))
                i += 1
                try:
                    self.sc.validate(p)
                except InfeasibleProblemError:
                    continue
                out.append((s, p))
            if not out:
                raise CheckFailure(f"validate() rejected all of {i} sampled problems")
            self._problems = out
        return self._problems

    def controls(self, H: int) -> np.ndarray:
        """Random controls of the declared control magnitudes (H, m)."""
        return self.rng.normal(size=(H, self.sc.control_dim)) * self.su

    def reference(self, problem: Problem) -> tuple[np.ndarray, np.ndarray]:
        """A dynamically consistent full-horizon reference: random controls rolled out from x0."""
        U = self.controls(problem.n_steps)
        return self.sc.rollout(problem, U), U

    def windows(self, problem: Problem) -> list[Window]:
        """The full horizon and a late receding-horizon window (MPC's windows start anywhere)."""
        N = problem.n_steps
        late = max(N // 2, N - 10)
        return [Window.full(problem), Window(late, N - late, N)]


def _fail(message: str) -> NoReturn:
    raise CheckFailure(message)


def _worst(err: np.ndarray) -> tuple[tuple[int, ...], float]:
    """Index and value of the largest entry: a failure names where it is worst."""
    idx = np.unravel_index(int(np.argmax(err)), err.shape)
    return tuple(int(i) for i in idx), float(err[idx])


# --------------------------------------------------------------------------------------------------------- checks
def _interface(ctx: _Context) -> str:
    sc = ctx.sc
    n, m, N = sc.state_dim, sc.control_dim, sc.n_steps
    for attr in ("name", "version"):
        if not isinstance(getattr(sc, attr, None), str):
            _fail(f"'{attr}' must be a string class attribute")
    for attr, size in (("state_dim", n), ("control_dim", m), ("n_steps", N)):
        if not isinstance(size, int) or size < 1:
            _fail(f"{attr} must be a positive int, got {size!r}")
    if getattr(sc, "cost_norm", None) not in get_args(CostNorm):
        _fail(f"cost_norm must be one of {get_args(CostNorm)}, got {getattr(sc, 'cost_norm', None)!r}")
    if getattr(sc, "trust_norm", None) not in ("l2", "linf"):
        _fail(f"trust_norm must be 'l2' or 'linf', got {getattr(sc, 'trust_norm', None)!r}")
    scp = getattr(sc, "scp", None)
    if not isinstance(scp, SCPSettings):
        _fail("scp must be an SCPSettings (trust region, iterations, penalty, feasibility tolerance)")
    ok = scp.max_iters >= 1 and scp.penalty > 0 and scp.feas_tol > 0
    if not (0 < scp.tr_end <= scp.tr_start and ok):
        _fail(f"scp needs 0 < tr_end <= tr_start, max_iters >= 1, penalty > 0 and feas_tol > 0, got {scp}")
    mpc = getattr(sc, "mpc", None)
    if not isinstance(mpc, MPCWeights):
        _fail("mpc must be an MPCWeights (fuel, end, terminal, dist)")
    if len(mpc.dist) != n:
        _fail(f"mpc.dist has {len(mpc.dist)} weights for {n} states")
    for attr, size in (("state_labels", n), ("control_labels", m), ("state_scale", n), ("control_scale", m)):
        value = tuple(getattr(sc, attr, ()))
        if attr.endswith("scale") and not value:
            continue
        if len(value) != size:
            _fail(f"{attr} has {len(value)} entries for dimension {size}")
        if attr.endswith("scale") and not all(np.isfinite(v) and v > 0 for v in value):
            _fail(f"{attr} must be positive and finite, got {value}")
    perturbation = tuple(sc.perturbation)
    if len(perturbation) != 3 or not all(np.isfinite(v) and v >= 0 for v in perturbation):
        _fail(f"perturbation must be (gain_std, actuation_std, process_std), 3 numbers >= 0, got {perturbation}")
    if any(not 0 <= r < n for r in sc.approximate_rows):
        _fail(f"approximate_rows {sc.approximate_rows} are not state rows 0..{n - 1}")
    return f"{sc.name} v{sc.version}: {n} states, {m} controls, N = {N}, cost {sc.cost_norm}"


def _sample(ctx: _Context) -> str:
    sc = ctx.sc
    n = sc.state_dim
    s = problem_seed(ctx.seed, 0)
    a, b = sc.sample(np.random.default_rng(s)), sc.sample(np.random.default_rng(s))
    if not (np.array_equal(a.x0, b.x0) and np.array_equal(a.goal, b.goal) and a.dt == b.dt):
        _fail("sample() gave two different problems for the same seed: draw only from the rng it is given")
    for i in range(20):
        p = sc.sample(np.random.default_rng(problem_seed(ctx.seed, i)))
        if not isinstance(p, Problem):
            _fail(f"sample() returned {type(p).__name__}, not a Problem")
        if p.x0.shape != (n,) or p.n_steps != sc.n_steps:
            _fail(f"problem {i}: x0 {p.x0.shape} and n_steps {p.n_steps}, expected ({n},) and {sc.n_steps}")
    problems = ctx.problems()
    return f"{len(problems)} valid problems, reproducible per seed"


def _features(ctx: _Context) -> str:
    sc = ctx.sc
    for s, p in ctx.problems():
        feats = {k: np.asarray(v, dtype=np.float64) for k, v in sc.problem_features(p).items()}  # as stored
        q = sc.problem_from_features(p.x0, p.goal, p.dt, feats)
        if q.n_steps != p.n_steps or q.dt != p.dt or not np.allclose(q.goal, p.goal, atol=1e-12):
            _fail(f"problem seed {s}: problem_from_features(x0, goal, dt, problem_features(p)) differs from p")
        u = ctx.controls(1)[0]
        if not np.allclose(sc.step(q, 0, q.x0, u), sc.step(p, 0, p.x0, u), rtol=1e-12, atol=0):
            _fail(f"problem seed {s}: the rebuilt problem steps differently (a parameter is not in problem_features)")
        X, _ = ctx.reference(p)
        back = sc.from_model_states(p, sc.to_model_states(p, X))
        (k, i), err = _worst(np.abs(back - X) / ctx.sx)
        if err > MODEL_TOL:
            _fail(f"problem seed {s}: from_model_states(to_model_states(X)) differs at step {k}, state {i} ({err:.1e})")
    return "problems rebuild from their stored features; representation maps invert each other"


def _model_error(ctx: _Context, p: Problem, w: Window, model: ConvexModel, X: np.ndarray, U: np.ndarray) -> np.ndarray:
    """|A x + B u + c − step(x, u)| per window step and state (H, n), in units of ``state_scale``."""
    pred = np.einsum("jab,jb->ja", model.A, X[:-1]) + np.einsum("jab,jb->ja", model.B, U) + model.c
    return np.abs(pred - ctx.sc.step_window(p, w.start, X[:-1], U)) / ctx.sx


def _convex_model(ctx: _Context) -> str:
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
                _fail(f"window {w.start}+{H}: A {model.A.shape}, B {model.B.shape}, c {model.c.shape}, expected "
                      f"({H}, {n}, {n}), ({H}, {n}, {m}), ({H}, {n})")  # fmt: skip
            for label, M, mask in (("A", model.A, model.A_mask), ("B", model.B, model.B_mask)):
                if mask is not None and np.any(M[:, ~np.asarray(mask, bool)] != 0):
                    (j, r, c), _ = _worst(np.abs(M * ~np.asarray(mask, bool)))
                    _fail(f"{label}[{j}][{r}, {c}] is nonzero outside {label}_mask (window {w.start}+{H})")
            (j, i), err = _worst(_model_error(ctx, p, w, model, X, U))
            if err > MODEL_TOL:
                _fail(f"A x + B u + c differs from step() at the reference it was built on: step {w.start + j}, "
                      f"state {i}, {err:.2e} in units of state_scale (problem seed {s})")  # fmt: skip
            Xp = X + ctx.rng.normal(size=X.shape) * ctx.sx * 0.1
            Up = U + ctx.rng.normal(size=U.shape) * ctx.su * 0.1
            away = _model_error(ctx, p, w, model, Xp, Up)
            rows, what = (np.arange(n), "exact_linear_dynamics is set") if sc.exact_linear_dynamics else (
                exact_rows, "it is not in approximate_rows")  # fmt: skip
            if len(rows) and away[:, rows].max() > MODEL_TOL:
                (j, i), err = _worst(away[:, rows])
                _fail(f"state row {rows[i]} of the affine model is not exact away from the reference ({err:.2e} "
                      f"at step {w.start + j}) but {what} (problem seed {s})")  # fmt: skip
    return "A x + B u + c reproduces step() at the reference" + (
        "" if not sc.exact_linear_dynamics else ", and everywhere (exact linear dynamics)"
    )


def _jacobian(ctx: _Context) -> str:
    sc = ctx.sc
    n, m = sc.state_dim, sc.control_dim
    for s, p in ctx.problems():
        X, U = ctx.reference(p)
        w = Window.full(p)
        model = sc.convex_model(p, w, X, U)
        for j in sorted({0, p.n_steps // 2, p.n_steps - 1}):
            x, u = X[j], U[j]
            hx, hu = 1e-6 * np.maximum(ctx.sx, np.abs(x)), 1e-6 * np.maximum(ctx.su, np.abs(u))
            Jx = np.stack([(sc.step(p, j, x + hx[i] * e, u) - sc.step(p, j, x - hx[i] * e, u)) / (2 * hx[i])
                           for i, e in enumerate(np.eye(n))], axis=1)  # fmt: skip
            Ju = np.stack([(sc.step(p, j, x, u + hu[i] * e) - sc.step(p, j, x, u - hu[i] * e)) / (2 * hu[i])
                           for i, e in enumerate(np.eye(m))], axis=1)  # fmt: skip
            for label, got, fd, col in (("A", model.A[j], Jx, ctx.sx), ("B", model.B[j], Ju, ctx.su)):
                err = np.abs(got - fd) * col[None, :] / ctx.sx[:, None]  # in units of the scales
                (r, c), worst = _worst(err)
                if worst > JACOBIAN_TOL:
                    _fail(f"{label}[{r}, {c}] at step {j} is {got[r, c]:.6g} but finite differences of step() "
                          f"give {fd[r, c]:.6g} (problem seed {s})")  # fmt: skip
    return "A and B match central finite differences of step()"


def _probe_states(ctx: _Context, p: Problem) -> np.ndarray:
    """States (N+1, n) that cross keep-out zones: the straight line to the goal, with the declared zones' centres
    (and points just inside their boundary) written over some of its states."""
    X = ctx.sc.initial_guess(p)[0].copy()
    centres, radii = ctx.sc.keepout_zones(p)
    k = 1
    for c, r in zip(np.asarray(centres, float), np.asarray(radii, float), strict=True):
        for point in (c, c + 0.9 * r * np.eye(len(c))[0]):
            if k < len(X) - 1:
                X[k, : len(c)] = point
                k += 2
    return X


def _batched_model(ctx: _Context) -> str:
    import torch

    sc = ctx.sc
    pairs = ctx.problems()
    problems = [p for _, p in pairs]
    model = sc.batched_model(problems)
    N = problems[0].n_steps
    for k in sorted({0, N // 2, N - 1}):
        X = np.stack([ctx.reference(p)[0][k] for p in problems])
        U = ctx.controls(len(problems))
        S = np.stack([sc.to_model_states(p, x[None], start=k)[0] for p, x in zip(problems, X, strict=True)])
        expected = np.stack(
            [sc.to_model_states(p, sc.step(p, k, x, u)[None], start=k + 1)[0]
             for p, x, u in zip(problems, X, U, strict=True)]
        )  # fmt: skip
        got = model.step(torch.as_tensor(S), torch.as_tensor(U), k)
        if tuple(got.shape) != expected.shape or got.dtype != torch.float64:
            _fail(f"step(S, A, {k}) returned {tuple(got.shape)} {got.dtype} for float64 states {expected.shape}")
        scale = np.abs(expected).max(axis=0) + 1.0
        (b, i), err = _worst(np.abs(got.numpy() - expected) / scale)
        if err > MODEL_TOL:
            _fail(f"step() at step {k}, state {i} is {got.numpy()[b, i]:.6g} but the scenario's step gives "
                  f"{expected[b, i]:.6g} (problem seed {pairs[b][0]})")  # fmt: skip
    for s, p in pairs:
        X = _probe_states(ctx, p)
        states = torch.as_tensor(sc.to_model_states(p, X))
        counts = np.asarray(sc.violations(p, X))
        for k in range(len(X)):
            got_count = float(model.violations(states[k : k + 1], k)[0])
            if got_count != counts[k]:
                _fail(f"violations(S, {k}) counts {got_count:g} but the scenario's violations() {counts[k]} "
                      f"(problem seed {s})")  # fmt: skip
    return "torch step and violation counts match step() and violations()"


def _structure(blocks: Sequence[ConstraintBlock]) -> list[tuple[Any, ...]]:
    return [
        (b.name, b.kind, b.steps.tolist(), b.Gx.shape, None if b.Gu is None else b.Gu.shape, b.nonconvex,
         b.obstacle, b.soft, b.lower is None)
        for b in blocks
    ]  # fmt: skip


def _constraints(ctx: _Context) -> str:
    sc = ctx.sc
    total = 0
    for _, p in ctx.problems():
        X_all, U_all = ctx.reference(p)
        for w in ctx.windows(p):
            H = w.length
            X1, U1 = sc.initial_guess(p, w)
            X2, U2 = X_all[w.start : w.stop + 1], U_all[w.start : w.stop]
            for obstacles in (True, False):
                b1 = sc.constraints(p, w, X1, U1, obstacles=obstacles)
                b2 = sc.constraints(p, w, X2, U2, obstacles=obstacles)
                if _structure(b1) != _structure(b2):
                    _fail(f"block shapes or steps change with the reference (window {w.start}+{H}, obstacles="
                          f"{obstacles}): they may depend only on the window")  # fmt: skip
                for b in b1:
                    where = f"block {b.name!r} (window {w.start}+{H})"
                    if b.steps.min(initial=0) < 0 or b.steps.max(initial=0) > H:
                        _fail(f"{where}: steps outside 0..{H}")
                    if b.Gu is not None and b.steps.max(initial=0) >= H:
                        _fail(f"{where}: a block with controls (Gu) uses state {H}, which has no control")
                    if b.obstacle and (not b.nonconvex or 0 in b.steps.tolist()):
                        _fail(f"{where}: a keep-out block must be nonconvex and leave out the fixed state 0")
                    if not obstacles and b.obstacle:
                        _fail(f"{where}: obstacle block returned with obstacles=False (REL)")
                    arrays = [b.Gx, b.h] + ([b.Gu] if b.Gu is not None else [])
                    if not all(np.all(np.isfinite(a)) for a in arrays):
                        _fail(f"{where}: non-finite values")
                    for label, G, mask in (("Gx", b.Gx, b.Gx_mask), ("Gu", b.Gu, b.Gu_mask)):
                        if G is not None and mask is not None and np.any(G[:, ~np.asarray(mask, bool)] != 0):
                            _fail(f"{where}: {label} is nonzero outside {label}_mask")
                total += len(b1)
    return f"block structure independent of the reference ({total} blocks checked)"


def _violations(ctx: _Context) -> str:
    sc = ctx.sc
    tol = sc.scp.feas_tol
    seen = 0
    for s, p in ctx.problems():
        X = _probe_states(ctx, p)
        counts = np.asarray(sc.violations(p, X))
        if counts.shape != (len(X),) or counts.dtype.kind not in "iu":
            _fail(f"violations() returned {counts.dtype} {counts.shape}, expected int ({len(X)},)")
        N = p.n_steps
        for k in np.flatnonzero(counts[1:N]) + 1:
            seen += 1
            w = Window(int(k) - 1, 1, N)
            Xw, Uw = X[k - 1 : k + 1], np.zeros((1, sc.control_dim))
            depth = sc.path_violation(p, Xw, Uw, w, obstacles=True)
            if depth <= tol:
                _fail(f"state {k} counts {counts[k]} violation(s) but path_violation() is {depth:.2e} <= scp.feas_tol "
                      f"{tol:g}: SCP would accept it as feasible (problem seed {s})")  # fmt: skip
            blocks = [b for b in sc.constraints(p, w, Xw, Uw, obstacles=True) if b.obstacle]
            rows = [
                (np.einsum("kmn,kn->km", b.Gx, Xw[b.steps]) - b.h)[b.steps == 1]
                for b in blocks
                if b.kind is BlockKind.INEQ
            ]
            if not any(np.any(r > 0) for r in rows):
                _fail(f"state {k} counts {counts[k]} violation(s) but the keep-out rows linearised at it are all "
                      f"satisfied: SCP cannot see the zone (problem seed {s})")  # fmt: skip
    if not seen:
        return "no probe state inside a keep-out zone (declare keepout_zones() to probe them)"
    return f"{seen} violating probe states seen by path_violation() and by the linearised keep-out rows"


def _solve(ctx: _Context) -> str:
    sc = ctx.sc
    tol = sc.scp.feas_tol
    iters, times = [], []
    for s, p in ctx.problems():
        rel, scp = solve_problem(sc, p, backend=ctx.backend)
        if scp is None:
            _fail(f"problem seed {s}: REL {rel.status.value} after {rel.iterations} iteration(s) (violation "
                  f"{rel.violation:.2e}): the relaxed problem has no solution from this start")  # fmt: skip
        if not scp.success:
            _fail(f"problem seed {s}: SCP {scp.status.value} after {scp.iterations} iterations (violation "
                  f"{scp.violation:.2e} > feas_tol {tol:g})")  # fmt: skip
        err = float(np.max(np.abs(scp.X[-1] - p.goal)))
        count = int(np.sum(sc.violations(p, scp.X)))
        if err > tol or count:
            _fail(f"problem seed {s}: the SCP solution ends {err:.2e} from the goal with {count} keep-out "
                  "violation(s)")  # fmt: skip
        iters.append(scp.iterations)
        times.append(rel.solve_time + scp.solve_time)
    return f"{len(iters)} problems solved (SCP {np.mean(iters):.1f} iterations, {np.mean(times):.2f} s per problem)"


_CHECKS: dict[str, Callable[[_Context], str]] = {
    "interface": _interface,
    "sample": _sample,
    "features": _features,
    "convex_model": _convex_model,
    "jacobian": _jacobian,
    "batched_model": _batched_model,
    "constraints": _constraints,
    "violations": _violations,
    "solve": _solve,
}
