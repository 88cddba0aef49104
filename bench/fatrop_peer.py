"""The structure-exploiting peer of ``bench/solver_speed.py``: the free-flyer and quadrotor NLPs of
``ipopt_peer.py`` solved by fatrop (an interior-point solver for optimal control that factors the KKT system stage by
stage with a Riccati recursion) through CasADi's ``nlpsol('fatrop')``, built once and re-solved per problem as the
IPOPT peer is: REL from the straight line, then the full problem from the REL solution. Needs ``casadi`` ≥ 3.7 (the
``peer`` extra; its wheels ship fatrop).

Posed as fatrop's CasADi interface asks (``structure_detection='auto'``): the decision variables declared stage by
stage (x_k, then u_k), and the constraint rows stage by stage, each stage's gap-closing dynamics x_{k+1} − f(x_k, u_k)
first, then the constraints on (x_k, u_k) alone (x_0 = x0 in stage 0, x_N = goal in stage N); no row couples stages
other than the dynamics. The free-flyer's L1 cost goes through the split u = u⁺ − u⁻, u± ≥ 0 (``casadi_models.py``):
with per-stage slacks s ≥ ±u instead, fatrop hit its iteration limit (1,000) on 2 of 3 full free-flyer problems. The
control variables are in the scenario's ``control_scale`` units (Δv in 0.01 m/s on the free-flyer): in SI units the
free-flyer's Δv ≤ 0.005 m/s left fatrop over-regularising its Hessian near the optimum (dual infeasibility stuck at
2e-6, 1,000 iterations) on 1 of 20 problems; IPOPT, which scales its own convergence test, needs neither."""

from __future__ import annotations

import casadi_models as cm
import numpy as np
from casadi_models import PeerResult

from ttompc.scenarios.base import Problem, Scenario

# fatrop's defaults (IPOPT's: mu_init 0.1, bound_push = bound_frac = 1e-2). With the controls in the scenario's units
# no setting tried did better on both scenarios: mu_init 1e-2 took 82.7 / 33.8 iterations per problem (free-flyer /
# quadrotor, 20 problems), with bound_push = bound_frac = 1e-4 92.7 / 26.9, mu_init 1e-3 with those 104 / 29.4, the
# defaults 90.8 / 30.8. CasADi's jit (gcc -O2, minutes per NLP) saved 3–7% of the time per problem (SI units)
FATROP_OPTIONS = {
    "expand": True,
    "structure_detection": "auto",
    "print_time": False,
    "fatrop": {"print_level": 0},
}
PROFILE_KEYS = (
    "compute_sd_time",
    "eval_hess_time",
    "eval_jac_time",
    "eval_cv_time",
    "eval_grad_time",
    "eval_obj_time",
    "time_total",
)


class FatropProblem:
    """One parametric stage-wise NLP (x0, goal as parameters; X, U initial guesses per solve)."""

    def __init__(self, scenario_name: str, obstacles: bool, control_scale: np.ndarray) -> None:
        import casadi as ca

        opti = ca.Opti()
        N = cm.N_STEPS
        x0, goal = opti.parameter(cm.STATE_DIM), opti.parameter(cm.STATE_DIM)
        X, U, u_vars, cost = [], [], [], 0
        for k in range(N + 1):  # variables in stage order: x_k, then u_k
            X.append(opti.variable(cm.STATE_DIM))
            if k < N:
                u, variables, c = cm.control_variables(opti, scenario_name, 1, control_scale)
                U.append(u)
                u_vars.append(variables)
                cost += c
        for k in range(N + 1):  # rows in stage order: dynamics first, then the stage's own constraints
            if k < N:
                opti.subject_to(X[k + 1] == cm.next_states(scenario_name, X[k], U[k]))
            if k == 0:
                opti.subject_to(X[0] == x0)
            else:
                cm.state_constraints(opti, scenario_name, X[k], obstacles)
            if k < N:
                cm.control_constraints(opti, scenario_name, X[k], U[k], u_vars[k])
            else:
                opti.subject_to(X[N] == goal)
        opti.minimize(cost)
        opti.solver("fatrop", FATROP_OPTIONS)
        self.opti, self.X, self.U, self.u_vars, self.x0, self.goal = opti, X, U, u_vars, x0, goal
        self.control_scale = control_scale
        self.X_all, self.U_all = ca.horzcat(*X), ca.horzcat(*U)

    def solve(self, problem: Problem, X_init: np.ndarray, U_init: np.ndarray) -> PeerResult:
        opti = self.opti
        opti.set_value(self.x0, problem.x0)
        opti.set_value(self.goal, problem.goal)
        opti.set_initial(self.X_all, X_init.T)
        for k, variables in enumerate(self.u_vars):
            cm.set_control_guess(opti, variables, U_init[k][:, None], self.control_scale)
        result, stats = cm.solve_timed(opti, self.X_all, self.U_all)
        self.last_times = {key: float(stats["fatrop"][key]) for key in PROFILE_KEYS}
        return result


class FatropPeer:
    """REL then the full problem from the REL solution, both NLPs built once; ``profile`` sums fatrop's own timers
    (s) and iterations over the solves since it was last cleared."""

    def __init__(self, scenario: Scenario) -> None:
        self.scenario = scenario
        scale = np.asarray(scenario.control_scale, dtype=np.float64)
        self.rel = FatropProblem(scenario.name, obstacles=False, control_scale=scale)
        self.full = FatropProblem(scenario.name, obstacles=True, control_scale=scale)
        self.profile: dict[str, float] = {}

    def solve(self, problem: Problem) -> tuple[PeerResult, PeerResult]:
        X0, U0 = self.scenario.initial_guess(problem)
        rel = self.rel.solve(problem, X0, U0)
        full = self.full.solve(problem, rel.X, rel.U)
        for part, result in ((self.rel, rel), (self.full, full)):
            for key, value in {**part.last_times, "iterations": result.iterations}.items():
                self.profile[key] = self.profile.get(key, 0.0) + value
        return rel, full

    def profile_per_iteration(self) -> dict[str, float]:
        """ms per fatrop iteration in its search direction (the Riccati factorisation and solve), in the CasADi
        function evaluations (Hessian, Jacobian, constraints, gradient, objective) and in all (wall time)."""
        its = max(self.profile.get("iterations", 0.0), 1.0)
        evaluations = sum(self.profile.get(key, 0.0) for key in PROFILE_KEYS if key.startswith("eval_"))
        return {
            "search_direction_ms": 1e3 * self.profile.get("compute_sd_time", 0.0) / its,
            "evaluations_ms": 1e3 * evaluations / its,
            "total_ms": 1e3 * self.profile.get("time_total", 0.0) / its,
        }
