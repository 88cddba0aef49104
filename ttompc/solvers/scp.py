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

import numpy as np
from numpy.typing import ArrayLike

from ttompc.scenarios.base import Problem, Scenario, Window
from ttompc.solvers.engine import run_scp
from ttompc.solvers.problem import Formulation, SCPOptions, SCPProblem, check_problem
from ttompc.solvers.results import IterateRecord, SCPResult, SCPStatus, TerminalCost

__all__ = [
    "IterateRecord",
    "SCPOptions",
    "SCPProblem",
    "SCPResult",
    "SCPStatus",
    "TerminalCost",
    "solve_problem",
    "solve_rel",
    "solve_scp",
]


def solve_scp(scp: SCPProblem, X_init: ArrayLike, U_init: ArrayLike, options: SCPOptions | None = None) -> SCPResult:
    """Solve ``scp`` (the scenario's problem over its window, ``SCPProblem``) by SCP from the guess (X_init (H+1, n),
    U_init (H, m)) with ``options`` (default: the ``auto`` backend, the penalized formulation, the scenario's
    settings; ``SCPOptions``). X_init[0] is the window's fixed initial state.

    Build the descriptions once and update them per solve, e.g. in a receding-horizon loop::

        scp, options = SCPProblem(scenario, problem), SCPOptions(backend="clarabel")
        res = solve_scp(scp.update(window=window, terminal=terminal), X, U, options)
    """
    return run_scp(
        scp,
        np.asarray(X_init, dtype=np.float64),
        np.asarray(U_init, dtype=np.float64),
        options or SCPOptions(),
    )


def solve_rel(
    scenario: Scenario,
    problem: Problem,
    *,
    window: Window | None = None,
    x_start: np.ndarray | None = None,
    guess: tuple[np.ndarray, np.ndarray] | None = None,
    backend: str = "auto",
    formulation: Formulation = "penalized",
) -> SCPResult:
    """The REL relaxation (no keep-out constraints) of ``problem`` over ``window`` (default: the whole horizon) from
    ``x_start`` (default: x0), solved from the straight line; a single convex solve when the scenario's REL is convex
    (RPOD), otherwise SCP (free-flyer heading-dependent thruster bound, quadrotor drag). ``backend`` and
    ``formulation`` as in ``SCPOptions``.

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
    rel = SCPProblem(scenario, problem, window, obstacles=False)
    return solve_scp(rel, X0, U0, SCPOptions(backend=backend, formulation=formulation))


def solve_problem(
    scenario: Scenario, problem: Problem, *, backend: str = "auto", formulation: Formulation = "penalized"
) -> tuple[SCPResult, SCPResult | None]:
    """REL, then SCP warm-started from the REL solution: the two solutions a dataset stores per problem (paper
    §IV-B, §V). The SCP is skipped (None) when REL fails. ``backend`` and ``formulation`` as in ``SCPOptions``;
    arguments it cannot use are an ``InputError`` or ``ConfigError`` (``check_problem``, ``SCPOptions``)."""
    check_problem(scenario, problem)
    rel = solve_rel(scenario, problem, backend=backend, formulation=formulation)
    if not rel.success:
        return rel, None
    options = SCPOptions(backend=backend, formulation=formulation)
    return rel, solve_scp(SCPProblem(scenario, problem), rel.X, rel.U, options)
