"""The plan-tracking terminal weight a scenario needs (``MPCWeights.track``): the multipliers of the terminal
constraints of receding-horizon windows along open-loop optima.

A window [t, t+H) that tracks a plan pays w·‖x_{t+H} − x̄‖₂ instead of imposing x_{t+H} = x̄. By the exact-penalty
theorem the penalised window has the plan's own segment as its solution when w exceeds the dual norm (here the
2-norm) of a multiplier ν of the constraint x_{t+H} = x̄, i.e. the marginal cost of moving x̄; below that the window
trades the target for fuel and leaves even an exact plan. For each held-out problem this solves the open-loop
optimum (REL → SCP), then each window's convex problem linearised at the optimum (the MPC's soft-mode objective:
fuel weight ``mpc.fuel``, soft equalities; the plan's inequalities hard) with x_{t+H} = x̄ imposed, and reads
‖ν‖₂ from Clarabel through cvxpy. Multipliers are not unique where the problem is degenerate; any one bounds the
threshold from above. Printed per scenario: the largest ‖ν‖₂, where it occurs, its median, and the weight in use.

    python bench/tracking_weight.py [--scenarios freeflyer,quadrotor,rpod] [--problems 5] [--seed 0] [--horizon 10]
    python bench/tracking_weight.py --quick     # one problem, every 15th window (a smoke run)

Ends with one JSON line, also written to bench/results/tracking_weight.json.
"""

from __future__ import annotations

import argparse
from typing import Any

import cvxpy as cp
import numpy as np
from record import Machine, result_path, write_result

from ttompc.evaluation.problems import eval_problem
from ttompc.scenarios import get_scenario
from ttompc.scenarios.base import BlockKind, Problem, Scenario, Window
from ttompc.solvers import solve_problem

RESULTS = result_path("tracking_weight")


def terminal_multiplier(scenario: Scenario, problem: Problem, X: np.ndarray, U: np.ndarray, t: int, H: int) -> float:
    """‖ν‖₂ of x_{t+H} = X[t+H] in the window [t, t+H) linearised at the plan (X, U); nan if the solve fails."""
    w = Window(t, H, problem.n_steps)
    Xw, Uw = X[t : t + H + 1], U[t : t + H]
    model = scenario.convex_model(problem, w, Xw, Uw)
    n, m = scenario.state_dim, scenario.control_dim
    x, u = cp.Variable((H + 1, n)), cp.Variable((H, m))
    fuel = scenario.mpc.fuel
    if scenario.cost_norm == "l1":
        cost: Any = fuel * cp.sum(cp.abs(u))
    elif scenario.cost_norm == "l2":
        cost = fuel * cp.sum(cp.norm(u, 2, axis=1))
    else:
        cost = 0.5 * fuel * cp.sum_squares(u)
    terminal = x[H] == Xw[H]
    cons = [x[0] == Xw[0], terminal]
    cons += [x[j + 1] == model.A[j] @ x[j] + model.B[j] @ u[j] + model.c[j] for j in range(H)]
    for b in scenario.constraints(problem, w, Xw, Uw, obstacles=True):
        for kk, k in enumerate(b.steps):
            e = b.Gx[kk] @ x[k] + (b.Gu[kk] @ u[k] if b.Gu is not None else 0)
            if b.kind is BlockKind.SOC:
                cons.append(cp.norm(e[1:] - b.h[kk, 1:], 2) <= e[0] - b.h[kk, 0])
            elif b.kind is BlockKind.EQ:
                cost += b.weight * cp.norm(e - b.h[kk], 2)  # MPC soft mode
            else:  # the plan meets its linearised rows; a hair of slack keeps round-off from making them infeasible
                cons.append(e <= b.h[kk] + 1e-7)
                if b.lower is not None:
                    cons.append(e >= b.lower[kk] - 1e-7)
    prob = cp.Problem(cp.Minimize(cost), cons)
    prob.solve(solver="CLARABEL")
    if prob.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or terminal.dual_value is None:
        return float("nan")
    return float(np.linalg.norm(terminal.dual_value))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", default="freeflyer,quadrotor,rpod")
    ap.add_argument("--problems", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--horizon", type=int, default=10)
    ap.add_argument("--stride", type=int, default=1, help="every stride-th window (1: all)")
    ap.add_argument("--quick", action="store_true", help="one problem, every 15th window; writes no result file")
    ap.add_argument("--out", default=None, help="default: bench/results/tracking_weight.json (none with --quick)")
    args = ap.parse_args()
    if args.quick:
        args.problems, args.stride = 1, 15
    H = args.horizon
    results: dict[str, Any] = {}
    machine = Machine()
    print(f"{'scenario':>10} {'problem':>7} {'max |ν|':>8} {'at t':>5} {'median':>7} {'tracking':>8}")
    for name in args.scenarios.split(","):
        sc = get_scenario(name)
        per_problem = []
        for i in range(args.problems):
            ep = eval_problem(sc, args.seed, i, nonconvex_only=True)
            rel, scp = solve_problem(sc, ep.problem)
            best = scp if scp is not None and scp.success else rel
            ts = list(range(0, ep.problem.n_steps - H, args.stride))
            nu = np.array([terminal_multiplier(sc, ep.problem, best.X, best.U, t, H) for t in ts])
            k = int(np.nanargmax(nu))
            row = {
                "problem": i,
                "max": float(nu[k]),
                "at": ts[k],
                "median": float(np.nanmedian(nu)),
                "failed": int(np.sum(np.isnan(nu))),
            }
            per_problem.append(row)
            print(f"{name:>10} {i:>7} {row['max']:>8.3g} {row['at']:>5} {row['median']:>7.3g} {sc.mpc.tracking:>8.3g}")
        largest = max(r["max"] for r in per_problem)
        results[name] = {
            "max": largest,
            "tracking": sc.mpc.tracking,
            "target": sc.mpc.target,
            "exact": bool(sc.mpc.tracking > largest),
            "problems": per_problem,
        }
        verdict = "exceeds" if results[name]["exact"] else "does NOT exceed"
        print(f"{name}: tracking weight {sc.mpc.tracking:g} {verdict} the largest multiplier {largest:.3g}")
    summary = {
        "bench": "tracking_weight",
        "horizon": H,
        "seed": args.seed,
        "problems": args.problems,
        "stride": args.stride,
        "results": results,
        **machine.record(),
    }
    write_result(summary, args.out or (None if args.quick else RESULTS))


if __name__ == "__main__":
    main()
