"""The SCP iteration (see ``scp.py`` for the public API and the formulation); its subproblem solvers are
``ttompc.solvers.backends``."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np

from ttompc.errors import InputError
from ttompc.scenarios.base import BlockKind, ConstraintBlock, ConvexModel, SCPSettings
from ttompc.solvers.backends import SubproblemSolver, default_trust_norm, get_solver
from ttompc.solvers.problem import SCPOptions, SCPProblem
from ttompc.solvers.results import IterateRecord, SCPResult, SCPStatus, TerminalCost
from ttompc.solvers.spec import QuadraticTerminalCost, SubproblemData, SubproblemSpec


def run_scp(scp: SCPProblem, X_init: np.ndarray, U_init: np.ndarray, options: SCPOptions) -> SCPResult:
    """Solve ``scp`` by SCP from the float64 guess (X_init (H+1, n), U_init (H, m)); X_init[0] is the window's fixed
    first state. Each iteration linearises at the reference, solves the convex subproblem and moves the reference
    to its solution, until a fixed point (the stopping rule below), the iteration cap, or (reference formulation)
    an infeasible subproblem. Returns the best feasible iterate, else the least violating (``_Iterates``)."""
    t_start = time.perf_counter()
    sc = scp.scenario
    _check_guess(scp, X_init, U_init)
    if scp.window.start == 0:
        scp.scenario.validate(scp.problem)
    settings = _settings(scp, options)
    penalized = options.formulation == "penalized"
    use_tr = bool(np.isfinite(settings.tr_start))
    shrink = settings.shrink if use_tr else 1.0

    X_ref, U_ref = X_init.copy(), U_init.copy()
    x_start = X_init[0].copy()
    delta = settings.tr_start
    iterates = _Iterates(settings.feas_tol, settings.cost_tol)
    prev_merit: float | None = None
    status: SCPStatus | None = None  # None: the iteration cap
    solver: SubproblemSolver | None = None
    shapes: tuple = ()
    duals: dict[int, np.ndarray] = {}  # iteration -> its subproblem's costates, where the backend gives them

    for it in range(settings.max_iters):
        model, blocks = _linearise(scp, X_ref, U_ref, penalized)
        if solver is None:  # block structure depends only on the window (Scenario.constraints): one spec per solve
            prev_merit = _merit(scp, X_ref, U_ref, blocks, sc.cost(U_ref))  # the warm start's (the stopping rule)
            solver = _subproblem_solver(scp, options, settings, model, blocks)
            shapes = _shapes(blocks)
        elif _shapes(blocks) != shapes:
            raise ValueError(f"{scp.scenario.name}: constraint block shapes changed between SCP iterations")
        X, U, sol = solver.solve(_subproblem_data(scp, x_start, model, blocks, X_ref, delta))
        if X is None or U is None:
            iterates.history.append(
                IterateRecord(it, np.nan, np.nan, np.nan, np.nan, float(delta), sol.solve_time, sol.status)
            )
            # the reference formulation gives up on an infeasible subproblem, like the authors' code
            sub_failed = SCPStatus.INFEASIBLE if (sol.infeasible and not penalized) else SCPStatus.SOLVER_ERROR
            if sub_failed is SCPStatus.INFEASIBLE or iterates.best is None:
                status = sub_failed
            break
        cost = sc.cost(U)
        merit = _merit(scp, X, U, blocks, cost)
        violation = _violation(scp, X, U, blocks)
        step = float(np.max(np.linalg.norm(X - X_ref, axis=1)))
        iterates.add(IterateRecord(it, cost, merit, violation, step, float(delta), sol.solve_time, sol.status), X, U)
        if sol.costates is not None:
            duals[it] = sol.costates
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

    status, X_out, U_out, viol_out, best_it = iterates.outcome(status, penalized, X_init, U_init)
    return SCPResult(
        status=status,
        X=X_out,
        U=U_out,
        cost=iterates.history[best_it].cost if best_it >= 0 else sc.cost(U_out),  # the iterate's, computed once
        violation=float(viol_out),
        iterations=len(iterates.history),
        solve_time=time.perf_counter() - t_start,
        solver_time=sum(h.solver_time for h in iterates.history),
        window=scp.window,
        history=iterates.history,
        best_iteration=best_it,
        costates=_costates(duals.get(best_it), scp.scenario.state_dim),
    )


def _costates(duals: np.ndarray | None, n: int) -> np.ndarray | None:
    """The returned iterate's costates (H+1, n): its subproblem's dynamics multipliers for x_1..x_H (row 0, the
    fixed start, NaN); None where the backend gave none."""
    if duals is None:
        return None
    return np.concatenate([np.full((1, n), np.nan), duals])


@dataclass
class _Iterates:
    """A solve's iterates: their records, the best feasible one (lowest merit among those whose nonlinear violation
    is within ``feas_tol``; merits within ``tie_tol`` of the lowest count as equal, and the latest of them is the
    best, so noise below the stopping rule's tolerance does not choose between iterates of a flat valley) and the
    least violating one (the fallback when none is feasible)."""

    feas_tol: float
    tie_tol: float
    lowest: float = np.inf  # the lowest merit of a feasible iterate so far
    history: list[IterateRecord] = field(default_factory=list)
    best: tuple[np.ndarray, np.ndarray, float, int] | None = None  # (X, U, violation, iteration)
    least_bad: tuple[float, np.ndarray, np.ndarray, int] | None = None  # (violation, X, U, iteration)

    def add(self, record: IterateRecord, X: np.ndarray, U: np.ndarray) -> None:
        """Record the iterate (X, U) that ``record`` describes."""
        self.history.append(record)
        if record.violation <= self.feas_tol and record.objective <= self.lowest + self.tie_tol:
            self.best = (X, U, record.violation, record.iteration)
            self.lowest = min(self.lowest, record.objective)
        if self.least_bad is None or record.violation < self.least_bad[0]:
            self.least_bad = (record.violation, X, U, record.iteration)

    def outcome(
        self, status: SCPStatus | None, penalized: bool, X_init: np.ndarray, U_init: np.ndarray
    ) -> tuple[SCPStatus, np.ndarray, np.ndarray, float, int]:
        """The solve's status and what it returns (X, U, violation, iteration; the guess and -1 without an iterate)
        from the loop's ``status`` (None: the iteration cap): the best feasible iterate if any (OPTIMAL at a fixed
        point, else FEASIBLE; in the reference formulation not once a subproblem failed), else the least violating
        one."""
        failed = status in (SCPStatus.INFEASIBLE, SCPStatus.SOLVER_ERROR)
        if self.best is not None and (penalized or not failed):
            status = SCPStatus.OPTIMAL if status is SCPStatus.OPTIMAL else SCPStatus.FEASIBLE
        elif not failed:
            status = SCPStatus.INFEASIBLE if self.least_bad is not None else SCPStatus.SOLVER_ERROR
        assert status is not None  # each branch above sets it
        if self.best is not None and status in (SCPStatus.OPTIMAL, SCPStatus.FEASIBLE):
            X, U, violation, it = self.best
        elif self.least_bad is not None:
            violation, X, U, it = self.least_bad
        else:
            X, U, violation, it = X_init, U_init, float("inf"), -1
        return status, X, U, violation, it


def _check_guess(scp: SCPProblem, X_init: np.ndarray, U_init: np.ndarray) -> None:
    sc, H = scp.scenario, scp.window.length
    n, m = sc.state_dim, sc.control_dim
    if X_init.shape != (H + 1, n) or U_init.shape != (H, m):
        raise InputError(
            f"{sc.name}: warm start must have shapes ({H + 1}, {n}) and ({H}, {m}) for a window of {H} steps, "
            f"got {X_init.shape} and {U_init.shape}"
        )
    if not (np.isfinite(X_init).all() and np.isfinite(U_init).all()):
        raise InputError(f"{sc.name}: warm start contains non-finite values")


def _settings(scp: SCPProblem, options: SCPOptions) -> SCPSettings:
    """The options' settings, by default the scenario's, or one iteration without trust region where one
    subproblem solves the problem (``SCPProblem.convex``)."""
    if options.settings is not None:
        return options.settings
    return _single_solve(scp.scenario.scp) if scp.convex else scp.scenario.scp


def _single_solve(settings: SCPSettings) -> SCPSettings:
    """Settings for a convex problem: one iteration, no trust region."""
    return SCPSettings(
        tr_start=np.inf,
        tr_end=np.inf,
        max_iters=1,
        cost_tol=settings.cost_tol,
        penalty=settings.penalty,
        feas_tol=settings.feas_tol,
    )


def _linearise(
    scp: SCPProblem, X_ref: np.ndarray, U_ref: np.ndarray, penalized: bool
) -> tuple[ConvexModel, list[ConstraintBlock]]:
    """The scenario's convex model and constraint blocks at the reference; in the reference formulation every
    linearised constraint is hard."""
    model = scp.scenario.convex_model(scp.problem, scp.window, X_ref, U_ref)
    blocks = scp.scenario.constraints(scp.problem, scp.window, X_ref, U_ref, obstacles=scp.obstacles)
    if not penalized:
        blocks = [_hard(b) for b in blocks]
    return model, blocks


def _subproblem_solver(
    scp: SCPProblem,
    options: SCPOptions,
    settings: SCPSettings,
    model: ConvexModel,
    blocks: list[ConstraintBlock],
) -> SubproblemSolver:
    """The solver of this solve's subproblem structure, restarted. Solvers are cached per structure across solves
    (``get_solver``); restarting them makes this solve's result depend on its inputs only, not on the problems this
    process solved before (e.g. which pool worker a dataset problem landed on): regenerated rows are bit-identical."""
    sc, terminal = scp.scenario, scp.terminal
    penalized = options.formulation == "penalized"
    backend, trust_norm = _solver_path(scp, options)
    spec = SubproblemSpec(
        H=scp.window.length,
        n=sc.state_dim,
        m=sc.control_dim,
        cost_norm=sc.cost_norm,
        fuel_weight=float(scp.fuel_weight),
        penalized=penalized,
        virtual_control=penalized and not sc.exact_linear_dynamics,
        vc_rows=tuple(sc.approximate_rows),
        trust=trust_norm if np.isfinite(settings.tr_start) else "none",
        end_form=_end_form(terminal),
        soft_equalities=scp.soft,
        penalty=float(settings.penalty),
        blocks=tuple(SubproblemSpec.block_signature(b) for b in blocks),
        tr_states=tuple(int(j) for j in sc.trust_region_steps(scp.problem, scp.window, terminal is None)),
        state_scale=tuple(sc.state_scale),
        control_scale=tuple(sc.control_scale),
        model_masks=SubproblemSpec.model_signature(model),
        terminal_value=terminal is not None and terminal.value is not None,
    )
    solver = get_solver(spec, backend, sc)
    solver.restart()
    return solver


def _solver_path(scp: SCPProblem, options: SCPOptions) -> tuple[str, str]:
    """The backend and trust-region norm that ``options`` run (``SCPOptions``)."""
    if options.formulation == "reference" and options.backend == "auto":  # the reference's path (docs/benchmarks.md)
        # certified infeasibility matters for the reference formulation (QOCO reports errors); its 2-norm trust region
        return "clarabel", "l2"
    return options.backend, default_trust_norm(options.backend, scp.scenario)


def _subproblem_data(
    scp: SCPProblem,
    x_start: np.ndarray,
    model: ConvexModel,
    blocks: list[ConstraintBlock],
    X_ref: np.ndarray,
    delta: float,
) -> SubproblemData:
    """The subproblem's data at the reference ``X_ref`` with trust radius ``delta``."""
    terminal = scp.terminal
    norm = terminal if terminal is not None and terminal.has_norm else None
    local = None
    if terminal is not None and terminal.value is not None:  # the cost-to-go's local model about the reference,
        e, w = terminal.value.expand(X_ref[-1]), scp.fuel_weight  # weighted as the stage cost (``TerminalCost``)
        local = QuadraticTerminalCost(hessian=w * e.hessian, gradient=w * e.gradient, center=np.array(X_ref[-1]))
    return SubproblemData(
        x_start=x_start,
        model=model,
        blocks=blocks,
        X_ref=X_ref,
        delta=float(delta),
        goal=scp.problem.goal,
        terminal_target=None if norm is None else norm.target,
        terminal_weights=None if norm is None else norm.weights,
        terminal_cost=local,
    )


def _end_form(terminal: TerminalCost | None) -> str:
    """The subproblem's end form (``SubproblemSpec.end_form``): "hard" (x_N = goal), "soft" (the 2-norm term's
    cone, with a cost-to-go model where the term has a value) or "value" (the cost-to-go model alone)."""
    if terminal is None:
        return "hard"
    return "soft" if terminal.has_norm else "value"


def _merit(scp: SCPProblem, X: np.ndarray, U: np.ndarray, blocks: list[ConstraintBlock], cost: float) -> float:
    """Weighted stage cost + soft terminal term + soft equality penalties of a window trajectory whose stage cost
    Σ c(u_k) is ``cost`` (the caller's, computed once per iterate)."""
    terminal = 0.0 if scp.terminal is None else scp.terminal(X[-1], scp.fuel_weight)
    return scp.fuel_weight * cost + terminal + _soft_eq_term(blocks, X, U, scp.soft)


def _violation(scp: SCPProblem, X: np.ndarray, U: np.ndarray, blocks: list[ConstraintBlock]) -> float:
    """The iterate's nonlinear violation: the scenario's constraints, x_N = goal where the window keeps it hard,
    and the equality rows unless soft mode prices them."""
    violation = scp.scenario.constraint_violation(scp.problem, X, U, scp.window, obstacles=scp.obstacles)
    if scp.terminal is None:
        violation = max(violation, float(np.max(np.abs(X[-1] - scp.problem.goal))))
    if not scp.soft:
        violation = max(violation, _eq_residual(blocks, X, U))
    return violation


def _shapes(blocks: list[ConstraintBlock]) -> tuple:
    return tuple((b.name, b.Gx.shape, None if b.Gu is None else b.Gu.shape, b.lower is None) for b in blocks)


def _hard(block: ConstraintBlock) -> ConstraintBlock:
    return dataclasses.replace(block, soft=False) if block.soft else block


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
