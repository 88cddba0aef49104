"""The peer to beat in ``bench/solver_speed.py``: the free-flyer and quadrotor problems as non-convex NLPs solved
directly by IPOPT through CasADi, each built once as a parametric ``Opti`` problem with ``expand=True`` (SX
function graphs), then re-solved per problem with new parameters and initial guesses: REL (no keep-out) from the
straight line, then the full problem from the REL solution, as our REL + SCP does. Needs ``casadi`` (the ``peer``
extra). The formulations are the scenarios' own: the same dynamics, bounds, keep-out radii and costs (the L1 cost
through u = u⁺ − u⁻, u± ≥ 0)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ttompc.scenarios import freeflyer as ff
from ttompc.scenarios import quadrotor as qr
from ttompc.scenarios.base import Problem, Scenario

IPOPT_OPTIONS = {"ipopt.print_level": 0, "ipopt.sb": "yes", "print_time": False, "expand": True}


@dataclass
class PeerResult:
    ok: bool
    X: np.ndarray  # (N+1, n)
    U: np.ndarray  # (N, m)
    iterations: int  # IPOPT iterations
    seconds: float


class IpoptProblem:
    """One parametric NLP (x0, goal as parameters; X, U initial guesses per solve)."""

    def __init__(self, scenario_name: str, obstacles: bool) -> None:
        import casadi as ca

        self.ca = ca
        opti = ca.Opti()
        N = 100
        X = opti.variable(6, N + 1)
        x0, goal = opti.parameter(6), opti.parameter(6)
        opti.subject_to(X[:, 0] == x0)
        opti.subject_to(X[:, N] == goal)
        if scenario_name == "freeflyer":
            Up, Um = opti.variable(3, N), opti.variable(3, N)
            U = Up - Um
            opti.subject_to(opti.bounded(0, ca.vec(Up), np.inf))
            opti.subject_to(opti.bounded(0, ca.vec(Um), np.inf))
            opti.minimize(ca.sum1(ca.sum2(Up + Um)))
            A, B = ca.DM(ff.A_STEP), ca.DM(ff.A_STEP @ ff.B_IMP)
            opti.subject_to(X[:, 1:] == A @ X[:, :N] + B @ U)
            for d in range(2):
                opti.subject_to(opti.bounded(ff.TABLE[0][d], X[d, 1:], ff.TABLE[1][d]))
            psi = X[2, :N]
            c, s = ca.cos(psi), ca.sin(psi)
            body = ca.vertcat(c * U[0, :] + s * U[1, :], -s * U[0, :] + c * U[1, :], U[2, :])
            dv = ca.DM(ff.LAMBDA_INV) @ body
            opti.subject_to(opti.bounded(-ff.DV_MAX, ca.vec(dv), ff.DV_MAX))
            if obstacles:
                for centre in ff.OBSTACLES:
                    d2 = (X[0, 1:] - centre[0]) ** 2 + (X[1, 1:] - centre[1]) ** 2
                    opti.subject_to(d2 >= ff.R_EFF**2)
            self.u_vars = (Up, Um)
        else:
            U = opti.variable(3, N)
            opti.subject_to(opti.bounded(-qr.U_MAX, ca.vec(U), qr.U_MAX))
            opti.minimize(0.5 * ca.sumsqr(U))
            v = X[3:, :N]
            speed = ca.sqrt(ca.sum1(v**2) + 1e-12)  # smooth at v = 0 (the drag is O(‖v‖²) there)
            drag = -(qr.DRAG / qr.MASS) * ca.repmat(speed, 3, 1) * v
            acc = U / qr.MASS + drag
            opti.subject_to(X[:, 1:] == X[:, :N] + qr.DT * ca.vertcat(v, acc))
            if obstacles:
                for centre, r in zip(qr.OBSTACLES, qr.OBSTACLE_RADII, strict=True):
                    d2 = sum((X[i, 1:] - centre[i]) ** 2 for i in range(3))
                    opti.subject_to(d2 >= r**2)
            self.u_vars = (U,)
        opti.solver("ipopt", IPOPT_OPTIONS)
        self.opti, self.X, self.U, self.x0, self.goal = opti, X, U, x0, goal

    def solve(self, problem: Problem, X_init: np.ndarray, U_init: np.ndarray) -> PeerResult:
        opti = self.opti
        opti.set_value(self.x0, problem.x0)
        opti.set_value(self.goal, problem.goal)
        opti.set_initial(self.X, X_init.T)
        if len(self.u_vars) == 2:
            opti.set_initial(self.u_vars[0], np.maximum(U_init, 0).T)
            opti.set_initial(self.u_vars[1], np.maximum(-U_init, 0).T)
        else:
            opti.set_initial(self.u_vars[0], U_init.T)
        t0 = time.perf_counter()
        try:
            sol = opti.solve()
            ok, getter = True, sol.value
        except RuntimeError:  # IPOPT did not converge; the debug values are the last iterate
            ok, getter = False, opti.debug.value
        seconds = time.perf_counter() - t0
        stats = opti.stats()
        X, U = np.asarray(getter(self.X)).T, np.asarray(getter(self.U)).T
        return PeerResult(ok and bool(stats.get("success", False)), X, U, int(stats.get("iter_count", -1)), seconds)


class IpoptPeer:
    """REL then the full problem from the REL solution, both NLPs built once."""

    def __init__(self, scenario: Scenario) -> None:
        self.scenario = scenario
        self.rel = IpoptProblem(scenario.name, obstacles=False)
        self.full = IpoptProblem(scenario.name, obstacles=True)

    def solve(self, problem: Problem) -> tuple[PeerResult, PeerResult]:
        X0, U0 = self.scenario.initial_guess(problem)
        rel = self.rel.solve(problem, X0, U0)
        full = self.full.solve(problem, rel.X, rel.U)
        return rel, full
