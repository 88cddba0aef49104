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
* ``jacobian``: A and B are the derivatives of ``step`` (central finite differences; these two and the next two
  checks of the dynamics' forms are in ``ttompc.scenario_check_dynamics``);
* ``batched_model``: the torch model steps like ``step`` and counts violations like ``violations``;
* ``fused_step``: the fused decoder's compiled step (where the batched model has one) steps like ``step``;
* ``constraints``: block shapes and steps do not depend on the reference, values are finite and within the masks,
  keep-out blocks are non-convex and skip the fixed state 0;
* ``violations``: every state counted as violating is seen by ``path_violation`` (beyond ``scp.feas_tol``) and by
  the linearised keep-out rows at that state;
* ``solve``: sampled problems are solved by REL then SCP, and the SCP solution reaches the goal with no violation.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, get_args

import numpy as np

from ttompc.scenario_check_base import MODEL_TOL, CheckContext, CheckFailure, fail, probe_states, worst
from ttompc.scenario_check_dynamics import batched_model, convex_model, fused_step, jacobian
from ttompc.scenarios.base import (
    BlockKind,
    ConstraintBlock,
    CostNorm,
    MPCWeights,
    Problem,
    Scenario,
    SCPSettings,
    Window,
)
from ttompc.scenarios.dynamics import CompiledScenario, CompiledStep
from ttompc.seeding import problem_seed
from ttompc.solvers.scp import solve_problem

CHECKS = (
    "interface",
    "sample",
    "features",
    "convex_model",
    "jacobian",
    "batched_model",
    "fused_step",
    "constraints",
    "violations",
    "solve",
)


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
    ctx = CheckContext(scenario, max(problems, 1), seed, backend)
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


# --------------------------------------------------------------------------------------------------------- checks
def _interface(ctx: CheckContext) -> str:
    sc = ctx.sc
    n, m, N = sc.state_dim, sc.control_dim, sc.n_steps
    for attr in ("name", "version"):
        if not isinstance(getattr(sc, attr, None), str):
            fail(f"'{attr}' must be a string class attribute")
    for attr, size in (("state_dim", n), ("control_dim", m), ("n_steps", N)):
        if not isinstance(size, int) or size < 1:
            fail(f"{attr} must be a positive int, got {size!r}")
    if getattr(sc, "cost_norm", None) not in get_args(CostNorm):
        fail(f"cost_norm must be one of {get_args(CostNorm)}, got {getattr(sc, 'cost_norm', None)!r}")
    if getattr(sc, "trust_norm", None) not in ("l2", "linf"):
        fail(f"trust_norm must be 'l2' or 'linf', got {getattr(sc, 'trust_norm', None)!r}")
    scp = getattr(sc, "scp", None)
    if not isinstance(scp, SCPSettings):
        fail("scp must be an SCPSettings (trust region, iterations, penalty, feasibility tolerance)")
    ok = scp.max_iters >= 1 and scp.penalty > 0 and scp.feas_tol > 0
    if not (0 < scp.tr_end <= scp.tr_start and ok):
        fail(f"scp needs 0 < tr_end <= tr_start, max_iters >= 1, penalty > 0 and feas_tol > 0, got {scp}")
    mpc = getattr(sc, "mpc", None)
    if not isinstance(mpc, MPCWeights):
        fail("mpc must be an MPCWeights (fuel, end, target, dist)")
    if len(mpc.dist) != n:
        fail(f"mpc.dist has {len(mpc.dist)} weights for {n} states")
    for attr, size in (("state_labels", n), ("control_labels", m), ("state_scale", n), ("control_scale", m)):
        value = tuple(getattr(sc, attr, ()))
        if attr.endswith("scale") and not value:
            continue
        if len(value) != size:
            fail(f"{attr} has {len(value)} entries for dimension {size}")
        if attr.endswith("scale") and not all(np.isfinite(v) and v > 0 for v in value):
            fail(f"{attr} must be positive and finite, got {value}")
    perturbation = tuple(sc.perturbation)
    if len(perturbation) != 3 or not all(np.isfinite(v) and v >= 0 for v in perturbation):
        fail(f"perturbation must be (gain_std, actuation_std, process_std), 3 numbers >= 0, got {perturbation}")
    if any(not 0 <= r < n for r in sc.approximate_rows):
        fail(f"approximate_rows {sc.approximate_rows} are not state rows 0..{n - 1}")
    if isinstance(sc, CompiledScenario) and not isinstance(getattr(sc, "dynamics", None), CompiledStep):
        got = type(getattr(sc, "dynamics", None)).__name__
        fail(f"a CompiledScenario declares dynamics = CompiledStep(its step function), got {got}")
    return f"{sc.name} v{sc.version}: {n} states, {m} controls, N = {N}, cost {sc.cost_norm}"


def _sample(ctx: CheckContext) -> str:
    sc = ctx.sc
    n = sc.state_dim
    s = problem_seed(ctx.seed, 0)
    a, b = sc.sample(np.random.default_rng(s)), sc.sample(np.random.default_rng(s))
    if not (np.array_equal(a.x0, b.x0) and np.array_equal(a.goal, b.goal) and a.dt == b.dt):
        fail("sample() gave two different problems for the same seed: draw only from the rng it is given")
    for i in range(20):
        p = sc.sample(np.random.default_rng(problem_seed(ctx.seed, i)))
        if not isinstance(p, Problem):
            fail(f"sample() returned {type(p).__name__}, not a Problem")
        if p.x0.shape != (n,) or p.n_steps != sc.n_steps:
            fail(f"problem {i}: x0 {p.x0.shape} and n_steps {p.n_steps}, expected ({n},) and {sc.n_steps}")
    problems = ctx.problems()
    return f"{len(problems)} valid problems, reproducible per seed"


def _features(ctx: CheckContext) -> str:
    sc = ctx.sc
    for s, p in ctx.problems():
        feats = {k: np.asarray(v, dtype=np.float64) for k, v in sc.problem_features(p).items()}  # as stored
        q = sc.problem_from_features(p.x0, p.goal, p.dt, feats)
        if q.n_steps != p.n_steps or q.dt != p.dt or not np.allclose(q.goal, p.goal, atol=1e-12):
            fail(f"problem seed {s}: problem_from_features(x0, goal, dt, problem_features(p)) differs from p")
        u = ctx.controls(1)[0]
        if not np.allclose(sc.step(q, 0, q.x0, u), sc.step(p, 0, p.x0, u), rtol=1e-12, atol=0):
            fail(f"problem seed {s}: the rebuilt problem steps differently (a parameter is not in problem_features)")
        X, _ = ctx.reference(p)
        back = sc.from_model_states(p, sc.to_model_states(p, X))
        (k, i), err = worst(np.abs(back - X) / ctx.sx)
        if err > MODEL_TOL:
            fail(f"problem seed {s}: from_model_states(to_model_states(X)) differs at step {k}, state {i} ({err:.1e})")
    return "problems rebuild from their stored features; representation maps invert each other"


def _structure(blocks: Sequence[ConstraintBlock]) -> list[tuple[Any, ...]]:
    return [
        (
            b.name,
            b.kind,
            b.steps.tolist(),
            b.Gx.shape,
            None if b.Gu is None else b.Gu.shape,
            b.nonconvex,
            b.obstacle,
            b.soft,
            b.lower is None,
        )
        for b in blocks
    ]


def _constraints(ctx: CheckContext) -> str:
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
                    fail(
                        f"block shapes or steps change with the reference (window {w.start}+{H}, obstacles="
                        f"{obstacles}): they may depend only on the window"
                    )
                for b in b1:
                    where = f"block {b.name!r} (window {w.start}+{H})"
                    if b.steps.min(initial=0) < 0 or b.steps.max(initial=0) > H:
                        fail(f"{where}: steps outside 0..{H}")
                    if b.Gu is not None and b.steps.max(initial=0) >= H:
                        fail(f"{where}: a block with controls (Gu) uses state {H}, which has no control")
                    if b.obstacle and (not b.nonconvex or 0 in b.steps.tolist()):
                        fail(f"{where}: a keep-out block must be nonconvex and leave out the fixed state 0")
                    if not obstacles and b.obstacle:
                        fail(f"{where}: obstacle block returned with obstacles=False (REL)")
                    arrays = [b.Gx, b.h] + ([b.Gu] if b.Gu is not None else [])
                    if not all(np.all(np.isfinite(a)) for a in arrays):
                        fail(f"{where}: non-finite values")
                    for label, G, mask in (("Gx", b.Gx, b.Gx_mask), ("Gu", b.Gu, b.Gu_mask)):
                        if G is not None and mask is not None and np.any(G[:, ~np.asarray(mask, bool)] != 0):
                            fail(f"{where}: {label} is nonzero outside {label}_mask")
                total += len(b1)
    return f"block structure independent of the reference ({total} blocks checked)"


def _violations(ctx: CheckContext) -> str:
    sc = ctx.sc
    tol = sc.scp.feas_tol
    seen = 0
    for s, p in ctx.problems():
        X = probe_states(ctx, p)
        counts = np.asarray(sc.violations(p, X))
        if counts.shape != (len(X),) or counts.dtype.kind not in "iu":
            fail(f"violations() returned {counts.dtype} {counts.shape}, expected int ({len(X)},)")
        N = p.n_steps
        for k in np.flatnonzero(counts[1:N]) + 1:
            seen += 1
            w = Window(int(k) - 1, 1, N)
            Xw, Uw = X[k - 1 : k + 1], np.zeros((1, sc.control_dim))
            depth = sc.path_violation(p, Xw, Uw, w, obstacles=True)
            if depth <= tol:
                fail(
                    f"state {k} counts {counts[k]} violation(s) but path_violation() is {depth:.2e} <= scp.feas_tol "
                    f"{tol:g}: SCP would accept it as feasible (problem seed {s})"
                )
            blocks = [b for b in sc.constraints(p, w, Xw, Uw, obstacles=True) if b.obstacle]
            rows = [
                (np.einsum("kmn,kn->km", b.Gx, Xw[b.steps]) - b.h)[b.steps == 1]
                for b in blocks
                if b.kind is BlockKind.INEQ
            ]
            if not any(np.any(r > 0) for r in rows):
                fail(
                    f"state {k} counts {counts[k]} violation(s) but the keep-out rows linearised at it are all "
                    f"satisfied: SCP cannot see the zone (problem seed {s})"
                )
    if not seen:
        return "no probe state inside a keep-out zone (declare keepout_zones() to probe them)"
    return f"{seen} violating probe states seen by path_violation() and by the linearised keep-out rows"


def _solve(ctx: CheckContext) -> str:
    sc = ctx.sc
    tol = sc.scp.feas_tol
    iters, times = [], []
    for s, p in ctx.problems():
        rel, scp = solve_problem(sc, p, backend=ctx.backend)
        if scp is None:
            fail(
                f"problem seed {s}: REL {rel.status.value} after {rel.iterations} iteration(s) (violation "
                f"{rel.violation:.2e}): the relaxed problem has no solution from this start"
            )
        if not scp.success:
            fail(
                f"problem seed {s}: SCP {scp.status.value} after {scp.iterations} iterations (violation "
                f"{scp.violation:.2e} > feas_tol {tol:g})"
            )
        err = float(np.max(np.abs(scp.X[-1] - p.goal)))
        count = int(np.sum(sc.violations(p, scp.X)))
        if err > tol or count:
            fail(f"problem seed {s}: the SCP solution ends {err:.2e} from the goal with {count} keep-out violation(s)")
        iters.append(scp.iterations)
        times.append(rel.solve_time + scp.solve_time)
    return f"{len(iters)} problems solved (SCP {np.mean(iters):.1f} iterations, {np.mean(times):.2f} s per problem)"


_CHECKS: dict[str, Callable[[CheckContext], str]] = {
    "interface": _interface,
    "sample": _sample,
    "features": _features,
    "convex_model": convex_model,
    "jacobian": jacobian,
    "batched_model": batched_model,
    "fused_step": fused_step,
    "constraints": _constraints,
    "violations": _violations,
    "solve": _solve,
}
