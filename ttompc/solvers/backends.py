"""Solver backends for the conic assembly of the subproblem (``subproblem.py``).

What ``backend="auto"`` runs (``engine.backend_chain``): PIQP on the compact QP form (``qp.py``, optional extra
``ttompc[fast]``) wherever the subproblem has no cone; otherwise QOCO (optional extra) with Clarabel as the fallback
on a numerical failure, or Clarabel alone where QOCO is not installed or the scenario asks for it (RPOD).

* ``qoco``: interior-point conic solver, the fastest measured here on our SOCPs; set up afresh per solve (below).
* ``clarabel``: interior-point conic solver shipped with cvxpy; handles the SOC trust region, the 2-norm costs
  (RPOD) and the approach cone. Data updates keep the KKT symbolic factorisation.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from ttompc.solvers.subproblem import AssembledSubproblem


@dataclass
class BackendSolution:
    z: np.ndarray | None
    objective: float
    ok: bool  # a usable (optimal or almost optimal) primal solution
    infeasible: bool  # the solver certified primal infeasibility
    status: str
    solve_time: float


class ClarabelBackend:
    name = "clarabel"
    supports_cones = True

    def __init__(self, sub: AssembledSubproblem) -> None:
        import clarabel

        self._clarabel = clarabel
        self.sub = sub
        self.settings = clarabel.DefaultSettings()
        self.settings.verbose = False
        self.settings.presolve_enable = False  # required for in-place data updates
        self.settings.input_sparse_dropzeros = False
        self.cones = []
        for kind, dim in sub.cones:
            if dim == 0:
                continue
            if kind == "zero":
                self.cones.append(clarabel.ZeroConeT(dim))
            elif kind == "nonneg":
                self.cones.append(clarabel.NonnegativeConeT(dim))
            else:
                self.cones.append(clarabel.SecondOrderConeT(dim))
        self.solver: Any = None  # clarabel.DefaultSolver, built on the first solve

    def restart(self) -> None:
        """Build the solver afresh on the next solve: ``update`` keeps the first data's equilibration, so an
        optimum would depend (at solver tolerance) on what was solved before."""
        self.solver = None

    def solve(self, a_values: np.ndarray, b: np.ndarray) -> BackendSolution:
        t0 = time.perf_counter()
        if self.solver is None:
            self.solver = self._clarabel.DefaultSolver(
                self.sub.P, self.sub.q, self.sub.matrix(a_values), b, self.cones, self.settings
            )
        else:
            self.solver.update(A=a_values, b=b)
        sol = self.solver.solve()
        elapsed = time.perf_counter() - t0
        status = str(sol.status)
        ok = status in ("Solved", "AlmostSolved")
        infeasible = "PrimalInfeasible" in status
        return BackendSolution(np.asarray(sol.x) if ok else None, float(sol.obj_val), ok, infeasible, status, elapsed)


class QOCOBackend:
    """QOCO (optional extra): min ½xᵀPx + cᵀx s.t. Ax = b, Gx ≤_C h with C = ℝ₊ˡ × SOCs. The zero-cone rows of
    the assembled matrix are QOCO's A, the rest its G.

    QOCO is set up afresh for every solve: its in-place updates keep the equilibration of the first data set and
    silently misalign values when that data had explicit zeros (measured: wrong optima on later problems), while a
    setup costs only a few percent of a solve here."""

    name = "qoco"
    supports_cones = True

    def __init__(self, sub: AssembledSubproblem) -> None:
        import qoco

        self._qoco = qoco
        self.sub = sub
        cones = dict((k, d) for k, d in sub.cones if k != "soc")
        self.n_zero, self.n_nonneg = cones["zero"], cones["nonneg"]
        self.soc_dims = np.array([d for k, d in sub.cones if k == "soc"], dtype=np.int64)
        self.P = sp.triu(sub.P, format="csc")
        self.blocks = sub.row_blocks(self.n_zero)  # QOCO's A (zero-cone rows) and G (the others)

    def restart(self) -> None:
        """Nothing to forget: QOCO is set up afresh for every solve."""

    def solve(self, a_values: np.ndarray, b: np.ndarray) -> BackendSolution:
        t0 = time.perf_counter()
        nz, sub = self.n_zero, self.sub
        A, G = (sp.csc_matrix((a_values[take], rows, ptr), shape=(m, sub.n_var)) for take, rows, ptr, m in self.blocks)
        solver = self._qoco.QOCO()
        solver.setup(
            sub.n_var,
            sub.n_con - nz,
            nz,
            self.P,
            sub.q,
            A,
            b[:nz],
            G,
            b[nz:],
            self.n_nonneg,
            len(self.soc_dims),
            self.soc_dims,
            verbose=False,
        )
        res = solver.solve()
        elapsed = time.perf_counter() - t0
        status = str(res.status)
        ok = status in ("QOCO_SOLVED", "QOCO_SOLVED_INACCURATE")
        return BackendSolution(
            np.asarray(res.x) if ok else None, float(res.obj), ok, "INFEAS" in status, status, elapsed
        )


BACKENDS: dict[str, type[ClarabelBackend | QOCOBackend]] = {"clarabel": ClarabelBackend, "qoco": QOCOBackend}
QP_BACKENDS = ("riccati", "piqp")  # solve QPs only: the trust region defaults to the ∞-norm for them
# every name ``backend=`` takes: the chains (``engine.backend_chain``), the solvers, and the naive cvxpy baseline
BACKEND_NAMES = ("auto", "conic", "riccati", "piqp", *BACKENDS, "cvxpy-naive")


def make_backend(name: str, sub: AssembledSubproblem) -> ClarabelBackend | QOCOBackend:
    try:
        cls = BACKENDS[name]
    except KeyError:
        raise ValueError(f"unknown solver backend {name!r}; choose from {list(BACKEND_NAMES)}") from None
    return cls(sub)


def cone_error(name: str) -> str:
    return (
        f"backend {name!r} solves QPs only, but this subproblem has second-order cones (2-norm cost, 2-norm trust "
        "region, approach cone or a soft terminal norm); use backend='auto', 'qoco' or 'clarabel', or trust_norm='linf'"
    )
