"""Conic solvers on the conic assembly of the subproblem (``ttompc.solvers.subproblem``), and
``AssembledSolver``, which runs them in order (a later one takes the subproblems an earlier one fails on).

* ``qoco``: interior-point conic solver, first in the conic chains (docs/design.md); set up afresh per solve (below).
* ``clarabel``: interior-point conic solver shipped with cvxpy; handles the SOC trust region, the 2-norm costs
  (RPOD) and the approach cone. Data updates keep the KKT symbolic factorisation.

Both return the multipliers of the dynamics rows as ``BackendSolution.costates`` (``AssembledSubproblem.costates``:
the riccati kernel's convention, ∂(optimum)/∂x_k per unit of the state) and take a terminal cost-to-go model in P
and q where the spec has one (``ttompc.solvers.objective``).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import scipy.sparse as sp

from ttompc.solvers.backends.base import BackendSolution
from ttompc.solvers.objective import ConicValues
from ttompc.solvers.spec import SubproblemData, SubproblemSpec
from ttompc.solvers.subproblem import AssembledSubproblem


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

    def solve(self, v: ConicValues) -> BackendSolution:
        t0 = time.perf_counter()
        if self.solver is None:
            self.solver = self._clarabel.DefaultSolver(
                self.sub.objective.matrix(v.P), v.q, self.sub.matrix(v.A), v.b, self.cones, self.settings
            )
        elif self.sub.spec.terminal_value:  # the terminal model's block and linear term change too
            self.solver.update(P=v.P, q=v.q, A=v.A, b=v.b)
        else:
            self.solver.update(A=v.A, b=v.b)
        sol = self.solver.solve()
        elapsed = time.perf_counter() - t0
        status = str(sol.status)
        ok = status in ("Solved", "AlmostSolved")
        infeasible = "PrimalInfeasible" in status
        return BackendSolution(
            np.asarray(sol.x) if ok else None,
            float(sol.obj_val),
            ok,
            infeasible,
            status,
            elapsed,
            self.sub.costates(sol.z) if ok else None,
        )


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
        self.blocks = sub.row_blocks(self.n_zero)  # QOCO's A (zero-cone rows) and G (the others)

    def restart(self) -> None:
        """Nothing to forget: QOCO is set up afresh for every solve."""

    def solve(self, v: ConicValues) -> BackendSolution:
        t0 = time.perf_counter()
        nz, sub, b = self.n_zero, self.sub, v.b
        A, G = (sp.csc_matrix((v.A[take], rows, ptr), shape=(m, sub.n_var)) for take, rows, ptr, m in self.blocks)
        solver = self._qoco.QOCO()
        solver.setup(
            sub.n_var,
            sub.n_con - nz,
            nz,
            sub.objective.matrix(v.P),
            v.q,
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
        duals = np.concatenate([res.y, res.z]) if ok else None  # the rows' order: A's (zero cone), then G's
        return BackendSolution(
            np.asarray(res.x) if ok else None,
            float(res.obj),
            ok,
            "INFEAS" in status,
            status,
            elapsed,
            None if duals is None else sub.costates(duals),
        )


BACKENDS: dict[str, type[ClarabelBackend | QOCOBackend]] = {"clarabel": ClarabelBackend, "qoco": QOCOBackend}


def make_backend(name: str, sub: AssembledSubproblem) -> ClarabelBackend | QOCOBackend:
    """The conic solver ``name`` (a key of ``BACKENDS``) on ``sub``; any other name is a ``ValueError``. Which
    names ``backend=`` takes is ``chain.BACKEND_NAMES``."""
    try:
        cls = BACKENDS[name]
    except KeyError:
        raise ValueError(f"unknown conic solver {name!r}; choose from {list(BACKENDS)}") from None
    return cls(sub)


class AssembledSolver:
    """Assembled structure + persistent backends: only values change between calls. With several backends the
    later ones are fallbacks for a numerical failure of the first (``auto``: QOCO, then Clarabel)."""

    def __init__(self, spec: SubproblemSpec, backends: Sequence[str]) -> None:
        self.sub = AssembledSubproblem(spec)
        self.backends = [make_backend(name, self.sub) for name in backends]

    def restart(self) -> None:
        for backend in self.backends:
            backend.restart()

    def solve(self, data: SubproblemData) -> tuple[np.ndarray | None, np.ndarray | None, BackendSolution]:
        """The first backend's usable solution of ``data`` (objective with the terminal model's constant, as the
        riccati backend's), else the last one's failure."""
        values = self.sub.update(data)
        spent = 0.0
        for backend in self.backends:
            sol = backend.solve(values)
            spent += sol.solve_time
            if sol.ok:
                break
        sol.solve_time = spent
        sol.objective += values.offset
        if sol.z is None:
            return None, None, sol
        X, U = self.sub.split(sol.z)
        return X, U, sol
