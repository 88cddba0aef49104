"""Sequential convex programming: one trust-region loop for REL and the full problem, every scenario, open loop
and receding horizon.

Each iteration linearises the scenario around the current reference, solves the convex subproblem (built once per
structure and updated in place, see ``subproblem.py``) and moves the reference. Two formulations:

* ``"penalized"`` (default, SCvx-style): every linearised/state constraint and the terminal condition get slack
  variables with an exact L1 penalty, plus virtual control on nonlinear dynamics, so each subproblem is feasible and
  the method never gives up on a solvable problem. Wherever the hard subproblem is feasible and the penalty exceeds
  its multipliers the two formulations take the same step, so costs match the reference where it succeeds.
* ``"reference"``: hard linearised constraints exactly as the authors' code; an infeasible subproblem ends the
  solve with status INFEASIBLE. Kept for comparisons (``bench/solver_speed.py``).

The result keeps the whole iterate history and returns the best feasible iterate (lowest cost among iterates whose
nonlinear violation is within tolerance), not merely the last one (the authors' code returned the last:
``docs/design.md``).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from ttompc.scenarios.base import Problem, Scenario, SCPSettings, Window
from ttompc.solvers.engine import run_scp
from ttompc.solvers.results import IterateRecord, SCPResult, SCPStatus, TerminalCost

__all__ = ["IterateRecord", "SCPResult", "SCPStatus", "TerminalCost", "solve_problem", "solve_rel", "solve_scp"]

Formulation = Literal["penalized", "reference"]
TrustNorm = Literal["l2", "linf"]


def solve_scp(
    scenario: Scenario,
    problem: Problem,
    X_init: np.ndarray,
    U_init: np.ndarray,
    *,
    window: Window | None = None,
    obstacles: bool = True,
    terminal: TerminalCost | None = None,
    fuel_weight: float = 1.0,
    soft_equalities: bool = False,
    settings: SCPSettings | None = None,
    backend: str = "auto",
    formulation: Formulation = "penalized",
    trust_norm: TrustNorm | None = None,
) -> SCPResult:
    """Solve the (windowed) problem by SCP from the guess (X_init (H+1, n), U_init (H, m)).

    X_init[0] is the fixed initial state of the window. Without ``terminal`` a window that reaches the end gets
    x_N = goal (hard, or penalised in the penalized formulation); windows that stop early need a ``terminal``.
    ``obstacles=False`` gives the REL relaxation. ``soft_equalities`` turns waypoint-type equalities into weighted
    2-norm penalties (MPC soft mode). ``backend``: "auto" (the scenario's chain: PIQP on subproblems without cones,
    QOCO/Clarabel on the others, see ``engine.backend_chain``), "conic" (QOCO then Clarabel throughout),
    "riccati" (opt-in, numba: the stage-wise interior-point kernel where the subproblem is a penalised QP, the
    ``auto`` chain elsewhere), "clarabel", "qoco", "piqp" or "cvxpy-naive" (the rebuild-every-iteration
    baseline). ``trust_norm`` defaults to the scenario's (``Scenario.trust_norm``; l2 for
    ``conic`` and for the reference formulation with ``auto``, the comparison paths).
    """
    window = window or Window.full(problem)
    return run_scp(
        scenario,
        problem,
        np.asarray(X_init, dtype=np.float64),
        np.asarray(U_init, dtype=np.float64),
        window=window,
        obstacles=obstacles,
        terminal=terminal,
        fuel_weight=fuel_weight,
        soft_equalities=soft_equalities,
        settings=settings or scenario.scp,
        backend=backend,
        formulation=formulation,
        trust_norm=trust_norm,
    )


def solve_rel(
    scenario: Scenario,
    problem: Problem,
    *,
    window: Window | None = None,
    x_start: np.ndarray | None = None,
    guess: tuple[np.ndarray, np.ndarray] | None = None,
    **kwargs,
) -> SCPResult:
    """The REL relaxation (no keep-out constraints) from the straight-line guess; a single convex solve when the
    scenario's REL is convex (RPOD), otherwise SCP (free-flyer heading-dependent thruster bound, quadrotor drag).

    ``guess`` (X (H+1, n), U (H, m)) replaces the straight line as the SCP's starting point (its X[0] is replaced by
    the window's first state), e.g. the previous receding-horizon step's REL plan shifted by one step: a converged
    guess costs one subproblem instead of three."""
    window = window or Window.full(problem)
    X0, U0 = scenario.initial_guess(problem, window, x_start)
    if guess is not None:
        X_g, U_g = np.array(guess[0], dtype=np.float64), np.array(guess[1], dtype=np.float64)
        if X_g.shape != X0.shape or U_g.shape != U0.shape:
            raise ValueError(
                f"{scenario.name}: REL guess must have shapes {X0.shape} and {U0.shape}, got {X_g.shape} and "
                f"{U_g.shape}"
            )
        X_g[0] = X0[0]
        X0, U0 = X_g, U_g
    if scenario.rel_is_convex:
        kwargs.setdefault("settings", _single_solve(kwargs.get("settings") or scenario.scp))
    return solve_scp(scenario, problem, X0, U0, window=window, obstacles=False, **kwargs)


def solve_problem(scenario: Scenario, problem: Problem, **kwargs) -> tuple[SCPResult, SCPResult | None]:
    """REL, then SCP warm-started from the REL solution: the two solutions a dataset stores per problem (paper
    §IV-B, §V). The SCP is skipped (None) when REL fails."""
    rel = solve_rel(scenario, problem, **kwargs)
    if not rel.success:
        return rel, None
    return rel, solve_scp(scenario, problem, rel.X, rel.U, **kwargs)


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
