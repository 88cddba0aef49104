"""The SCP iteration (see ``scp.py`` for the public API and the formulation); its subproblem solvers are
``ttompc.solvers.backends``."""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from ttompc.scenarios.base import BlockKind, ConstraintBlock, Problem, Scenario, SCPSettings, Window
from ttompc.solvers.backends import SubproblemSolver, default_trust_norm, get_solver
from ttompc.solvers.results import IterateRecord, SCPResult, SCPStatus, TerminalCost
from ttompc.solvers.subproblem import SubproblemData, SubproblemSpec


def run_scp(
    scenario: Scenario,
    problem: Problem,
    X_init: np.ndarray,
    U_init: np.ndarray,
    *,
    window: Window,
    obstacles: bool,
    terminal: TerminalCost | None,
    fuel_weight: float,
    soft_equalities: bool,
    settings: SCPSettings,
    backend: str,
    formulation: str,
    trust_norm: str | None,
) -> SCPResult:
    t_start = time.perf_counter()
    H, n, m = window.length, scenario.state_dim, scenario.control_dim
    if X_init.shape != (H + 1, n) or U_init.shape != (H, m):
        raise ValueError(
            f"{scenario.name}: warm start must have shapes ({H + 1}, {n}) and ({H}, {m}) for a window of {H} steps, "
            f"got {X_init.shape} and {U_init.shape}"
        )
    if not (np.all(np.isfinite(X_init)) and np.all(np.isfinite(U_init))):
        raise ValueError(f"{scenario.name}: warm start contains non-finite values")
    if formulation not in ("penalized", "reference"):
        raise ValueError(f"unknown SCP formulation {formulation!r}; choose 'penalized' or 'reference'")
    if terminal is None and not window.reaches_end:
        raise ValueError(f"window [{window.start}, {window.stop}) stops before the end and needs a terminal cost")
    if window.start == 0:
        scenario.validate(problem)
    penalized = formulation == "penalized"
    use_tr = bool(np.isfinite(settings.tr_start))
    if not penalized and backend == "auto":  # the reference's path, kept for comparisons (docs/benchmarks.md)
        backend = "clarabel"  # certified infeasibility matters for the reference formulation; QOCO reports errors
        trust_norm = trust_norm or "l2"  # the reference's 2-norm trust region
    if trust_norm is None:
        trust_norm = default_trust_norm(backend, scenario)
    shrink = settings.shrink if use_tr else 1.0

    X_ref, U_ref = X_init.copy(), U_init.copy()
    x_start = X_init[0].copy()
    delta = settings.tr_start
    history: list[IterateRecord] = []
    best: tuple[float, np.ndarray, np.ndarray, float, int] | None = None  # (merit, X, U, violation, iteration)
    least_bad: tuple[float, np.ndarray, np.ndarray, int] | None = None  # fallback: smallest violation
    prev_merit: float | None = None
    status: SCPStatus | None = None
    solver_time = 0.0
    solver: SubproblemSolver | None = None
    shapes: tuple = ()

    for it in range(settings.max_iters):
        model = scenario.convex_model(problem, window, X_ref, U_ref)
        blocks = scenario.constraints(problem, window, X_ref, U_ref, obstacles=obstacles)
        if not penalized:  # the reference formulation: every linearised constraint is hard
            blocks = [_hard(b) for b in blocks]
        if it == 0:  # the warm start's merit (see the stopping rule below)
            prev_merit = _merit(scenario, X_ref, U_ref, blocks, fuel_weight, terminal, soft_equalities)
        if solver is None:  # block structure depends only on the window (Scenario.constraints): one spec per solve
            spec = SubproblemSpec(
                H=H,
                n=n,
                m=m,
                cost_norm=scenario.cost_norm,
                fuel_weight=float(fuel_weight),
                penalized=penalized,
                virtual_control=penalized and not scenario.exact_linear_dynamics,
                vc_rows=tuple(scenario.approximate_rows),
                trust=trust_norm if use_tr else "none",
                terminal="hard" if terminal is None else "soft",
                finish=finish_kind(terminal),
                soft_equalities=soft_equalities,
                penalty=float(settings.penalty),
                blocks=tuple(SubproblemSpec.block_signature(b) for b in blocks),
                tr_states=tuple(int(j) for j in scenario.trust_region_steps(problem, window, terminal is None)),
                state_scale=tuple(scenario.state_scale),
                control_scale=tuple(scenario.control_scale),
                model_masks=SubproblemSpec.model_signature(model),
            )
            solver = get_solver(spec, backend, scenario)
            # Solvers are cached per structure across solves; restarting them makes this solve's result depend on
            # its inputs only, not on the problems this process solved before (e.g. which pool worker a dataset
            # problem landed on): regenerated rows are bit-identical.
            solver.restart()
            shapes = _shapes(blocks)
        elif _shapes(blocks) != shapes:
            raise ValueError(f"{scenario.name}: constraint block shapes changed between SCP iterations")
        data = SubproblemData(
            x_start=x_start,
            model=model,
            blocks=blocks,
            X_ref=X_ref,
            delta=float(delta),
            goal=problem.goal,
            terminal_target=None if terminal is None else terminal.target,
            terminal_weights=None if terminal is None else terminal.weights,
            finish=None if terminal is None else terminal.finish,
        )
        X, U, sol = solver.solve(data)
        solver_time += sol.solve_time
        if X is None or U is None:
            history.append(IterateRecord(it, np.nan, np.nan, np.nan, np.nan, float(delta), sol.solve_time, sol.status))
            # the reference formulation gives up on an infeasible subproblem, like the authors' code
            sub_failed = SCPStatus.INFEASIBLE if (sol.infeasible and not penalized) else SCPStatus.SOLVER_ERROR
            if sub_failed is SCPStatus.INFEASIBLE or best is None:
                status = sub_failed
            break
        cost = scenario.cost(U)
        merit = _merit(scenario, X, U, blocks, fuel_weight, terminal, soft_equalities)
        violation = scenario.constraint_violation(problem, X, U, window, obstacles=obstacles)
        if terminal is None:
            violation = max(violation, float(np.max(np.abs(X[-1] - problem.goal))))
        if not soft_equalities:
            violation = max(violation, _eq_residual(blocks, X, U))
        step = float(np.max(np.linalg.norm(X - X_ref, axis=1)))
        history.append(IterateRecord(it, cost, merit, violation, step, float(delta), sol.solve_time, sol.status))
        if violation <= settings.feas_tol and (best is None or merit < best[0]):
            best = (merit, X, U, violation, it)
        if least_bad is None or violation < least_bad[0]:
            least_bad = (violation, X, U, it)
        # a fixed point: the step from this iteration's linearisation point and the merit change from that point
        # are both below tolerance. The first iteration compares with the warm start, so a converged warm start
        # costs one subproblem, not two.
        flat = prev_merit is not None and abs(merit - prev_merit) <= settings.cost_tol
        converged = step <= settings.tr_end and flat
        X_ref, U_ref, prev_merit = X, U, merit
        delta *= shrink
        if converged or not use_tr:
            status = SCPStatus.OPTIMAL if violation <= settings.feas_tol else SCPStatus.INFEASIBLE
            break

    failed = status in (SCPStatus.INFEASIBLE, SCPStatus.SOLVER_ERROR)
    if best is not None and (penalized or not failed):
        status = SCPStatus.OPTIMAL if status is SCPStatus.OPTIMAL else SCPStatus.FEASIBLE
    elif not failed:
        status = SCPStatus.INFEASIBLE if least_bad is not None else SCPStatus.SOLVER_ERROR
    if best is not None and status in (SCPStatus.OPTIMAL, SCPStatus.FEASIBLE):
        _, X_out, U_out, viol_out, best_it = best
    elif least_bad is not None:
        viol_out, X_out, U_out, best_it = least_bad
    else:
        X_out, U_out, viol_out, best_it = X_init, U_init, float("inf"), -1
    assert status is not None  # each branch above sets it
    return SCPResult(
        status=status,
        X=X_out,
        U=U_out,
        cost=scenario.cost(U_out),
        violation=float(viol_out),
        iterations=len(history),
        solve_time=time.perf_counter() - t_start,
        solver_time=solver_time,
        window=window,
        history=history,
        best_iteration=best_it,
    )


def _merit(
    scenario: Scenario,
    X: np.ndarray,
    U: np.ndarray,
    blocks: list[ConstraintBlock],
    fuel_weight: float,
    terminal: TerminalCost | None,
    soft_equalities: bool,
) -> float:
    """Weighted stage cost + soft terminal term + soft equality penalties of a window trajectory."""
    return fuel_weight * scenario.cost(U) + _terminal_term(X, terminal) + _soft_eq_term(blocks, X, U, soft_equalities)


def _shapes(blocks: list[ConstraintBlock]) -> tuple:
    return tuple((b.name, b.Gx.shape, None if b.Gu is None else b.Gu.shape, b.lower is None) for b in blocks)


def _hard(block: ConstraintBlock) -> ConstraintBlock:
    return dataclasses.replace(block, soft=False) if block.soft else block


def _terminal_term(X: np.ndarray, terminal: TerminalCost | None) -> float:
    return 0.0 if terminal is None else terminal(X[-1])


def finish_kind(terminal: TerminalCost | None) -> str:
    """The subproblem's finish-cost structure: "none", "quad" (squared norm) or "norm"."""
    if terminal is None or terminal.finish is None:
        return "none"
    return "quad" if terminal.finish.squared else "norm"


def _eq_rows(block: ConstraintBlock, X: np.ndarray, U: np.ndarray) -> np.ndarray:
    """Residuals G x + G u − h of an equality block at the given window trajectory: (K, M)."""
    res = np.einsum("kmn,kn->km", block.Gx, X[block.steps]) - block.h
    if block.Gu is not None:
        res += np.einsum("kmu,ku->km", block.Gu, U[block.steps])
    return res


def _eq_residual(blocks: list[ConstraintBlock], X: np.ndarray, U: np.ndarray) -> float:
    return max((float(np.max(np.abs(_eq_rows(b, X, U)))) for b in blocks if b.kind is BlockKind.EQ), default=0.0)


def _soft_eq_term(blocks: list[ConstraintBlock], X: np.ndarray, U: np.ndarray, soft: bool) -> float:
    if not soft:
        return 0.0
    return sum(
        b.weight * float(np.sum(np.linalg.norm(_eq_rows(b, X, U), axis=1))) for b in blocks if b.kind is BlockKind.EQ
    )
