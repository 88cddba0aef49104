"""``ttompc solve``: sample a seeded problem, solve REL then SCP, print a table and optionally plot it."""

from __future__ import annotations

import argparse
import json

import numpy as np


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", default="freeflyer", help="scenario name (see `ttompc solve --list`)")
    p.add_argument("--seed", type=int, default=0, help="problem seed (numpy Generator)")
    p.add_argument("--backend", default="auto", help="auto|qoco|clarabel|osqp|piqp|cvxpy-naive")
    p.add_argument("--formulation", default="penalized", choices=["penalized", "reference"])
    p.add_argument("--plot", metavar="PNG", help="save a plot of the REL and SCP trajectories")
    p.add_argument("--json", action="store_true", help="print the results as JSON")
    p.add_argument("--list", action="store_true", help="list the registered scenarios and exit")


def run(args: argparse.Namespace) -> int:
    from ttompc.scenarios import get_scenario, list_scenarios
    from ttompc.solvers import solve_problem

    if args.list:
        print("\n".join(list_scenarios()))
        return 0
    scenario = get_scenario(args.scenario)
    problem = scenario.sample(np.random.default_rng(args.seed))
    rel, scp = solve_problem(scenario, problem, backend=args.backend, formulation=args.formulation)
    rows = {"REL": rel, "SCP": scp}
    results = {}
    for name, res in rows.items():
        if res is None:
            results[name] = {"status": "skipped (REL failed)"}
            continue
        X = res.X
        results[name] = {
            **res.summary(),
            "ctg0": int(scenario.violations(problem, X[:-1]).sum()),
            "feasible": bool(res.success and scenario.violations(problem, X[:-1]).sum() == 0),
        }
    if args.json:
        print(json.dumps({"scenario": scenario.name, "seed": args.seed, "results": results}, indent=2))
    else:
        print(f"{scenario.name} (v{scenario.version}), seed {args.seed}, cost = Σ {scenario.cost_norm}(u)")
        header = f"{'':4} {'status':>10} {'cost':>12} {'iters':>6} {'time [s]':>9} {'violation':>10} {'ctg0':>5}"
        print(header)
        for name, r in results.items():
            if "cost" not in r:
                print(f"{name:4} {r['status']}")
                continue
            print(
                f"{name:4} {r['status']:>10} {r['cost']:>12.6g} {r['iterations']:>6d} {r['solve_time']:>9.3f} "
                f"{r['violation']:>10.2e} {r['ctg0']:>5d}"
            )
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7, 5))
        trajs = {name: res.X for name, res in rows.items() if res is not None}
        scenario.plot(ax, problem, trajs)
        ax.set_title(f"{scenario.name} seed {args.seed}")
        fig.tight_layout()
        fig.savefig(args.plot, dpi=120)
        print(f"plot saved to {args.plot}")
    return 0 if (scp is not None and scp.success) else 1
