"""The peer to beat in ``bench/solver_speed.py``: the free-flyer and quadrotor problems as non-convex NLPs solved
directly by IPOPT through CasADi, each built once as a parametric ``Opti`` problem with ``expand=True`` (SX
function graphs), then re-solved per problem with new parameters and initial guesses: REL (no keep-out) from the
straight line, then the full problem from the REL solution, as our REL + SCP does. Needs ``casadi`` (the ``peer``
extra). The formulations are the scenarios' own (``casadi_models.py``): the same dynamics, bounds, keep-out radii
and costs (the L1 cost through u = u⁺ − u⁻, u± ≥ 0), over whole-trajectory variables."""

from __future__ import annotations

import casadi_models as cm
import numpy as np
from casadi_models import PeerResult

from ttompc.scenarios.base import Problem, Scenario

IPOPT_OPTIONS = {"ipopt.print_level": 0, "ipopt.sb": "yes", "print_time": False, "expand": True}


class IpoptProblem:
    """One parametric NLP (x0, goal as parameters; X, U initial guesses per solve)."""

    def __init__(self, scenario_name: str, obstacles: bool) -> None:
        import casadi as ca

        opti = ca.Opti()
        N = cm.N_STEPS
        X = opti.variable(cm.STATE_DIM, N + 1)
        U, self.u_vars, cost = cm.control_variables(opti, scenario_name, N)
        x0, goal = opti.parameter(cm.STATE_DIM), opti.parameter(cm.STATE_DIM)
        opti.subject_to(X[:, 0] == x0)
        opti.subject_to(X[:, N] == goal)
        opti.minimize(cost)
        opti.subject_to(X[:, 1:] == cm.next_states(scenario_name, X[:, :N], U))
        cm.control_constraints(opti, scenario_name, X[:, :N], U, self.u_vars)
        cm.state_constraints(opti, scenario_name, X[:, 1:], obstacles)
        opti.solver("ipopt", IPOPT_OPTIONS)
        self.opti, self.X, self.U, self.x0, self.goal = opti, X, U, x0, goal

    def solve(self, problem: Problem, X_init: np.ndarray, U_init: np.ndarray) -> PeerResult:
        opti = self.opti
        opti.set_value(self.x0, problem.x0)
        opti.set_value(self.goal, problem.goal)
        opti.set_initial(self.X, X_init.T)
        cm.set_control_guess(opti, self.u_vars, U_init.T)
        return cm.solve_timed(opti, self.X, self.U)[0]


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
