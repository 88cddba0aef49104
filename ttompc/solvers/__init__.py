"""One SCP engine for all scenarios (REL and full SCP), convex-subproblem backends, and the naive cvxpy baseline."""

from ttompc.solvers.scp import (
    IterateRecord,
    SCPOptions,
    SCPProblem,
    SCPResult,
    SCPStatus,
    TerminalCost,
    solve_problem,
    solve_rel,
    solve_scp,
)

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
