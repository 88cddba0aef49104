"""The subproblem solvers of the SCP engine, in one place.

* ``base``: the solver protocol (``SubproblemSolver``), its solution (``BackendSolution``) and ``Fallback``;
* ``conic``: QOCO and Clarabel on the conic assembly (``ttompc.solvers.subproblem``), ``AssembledSolver``;
* ``qp``: PIQP on the compact QP of subproblems without cones;
* ``riccati`` (its structs built per iteration, compiled by ``riccati_build``) / ``riccati_kernel`` with
  ``riccati_qp``, ``riccati_rows``, ``riccati_cone`` and ``riccati_jit``: the stage-wise interior point for penalised
  QP subproblems (numba), with a dense terminal cost-to-go block;
* ``chain``: what a ``backend=`` name runs (``backend_chain``), the trust-region norm it implies and the cache of
  built solver structures (``get_solver``).

What ``backend="auto"`` runs (``backend_chain``): the Riccati kernel on penalised QP subproblems, PIQP on the compact
QP of the other subproblems without cones (and where the kernel does not converge), else QOCO with Clarabel as the
fallback on a numerical failure (RPOD: Clarabel), with the scenario's trust-region norm (``Scenario.trust_norm``).
``backend="piqp"`` is the same chain without the kernel. Every solver, numba included, is a dependency: the default
does not depend on installed extras.
"""

from ttompc.solvers.backends.base import BackendSolution, SubproblemSolver
from ttompc.solvers.backends.chain import (
    BACKEND_NAMES,
    backend_chain,
    clear_solver_cache,
    default_trust_norm,
    get_solver,
    solver_path,
)

__all__ = [
    "BACKEND_NAMES",
    "BackendSolution",
    "SubproblemSolver",
    "backend_chain",
    "clear_solver_cache",
    "default_trust_norm",
    "get_solver",
    "solver_path",
]
