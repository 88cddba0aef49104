"""``ttompc demo``: the quickstart main job, offline. Load a shipped zoo model, plan a few seeded held-out problems
with REL vs transformer (TTO) warm starts of the full-horizon SCP, and close the loop with REL-MPC, DIST-MPC and
TTO-MPC at one planning horizon; print the comparison table and save a plot and a JSON summary."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", default="freeflyer-tto-small", help="zoo name, bundle directory or .ckpt")
    p.add_argument("--problems", type=int, default=2, help="held-out problems to plan")
    p.add_argument("--horizon", type=int, default=10, help="MPC planning horizon H")
    p.add_argument("--seed", type=int, default=0, help="root seed of the evaluation problem stream")
    p.add_argument("--no-mpc", action="store_true", help="open-loop warm starts only (fast)")
    p.add_argument("--out", default="outputs/demo", help="folder for demo.png and demo.json")


def run(args: argparse.Namespace) -> int:
    from ttompc.evaluation.common import eval_problem, single_torch_thread
    from ttompc.mpc.loop import run_mpc
    from ttompc.mpc.providers import DISTProvider, RELProvider, TTOProvider
    from ttompc.policy import Planner
    from ttompc.solvers import solve_scp

    planner = Planner.from_pretrained(args.model)
    scenario = planner.scenario
    print(
        f"model {args.model}: {scenario.name} v{scenario.version}, "
        f"{sum(p.numel() for p in planner.model.parameters()) / 1e6:.2f}M parameters"
    )
    rows: list[dict[str, Any]] = []
    plots = []
    with single_torch_thread():
        for i in range(args.problems):
            ep = eval_problem(scenario, args.seed, i, nonconvex_only=True)
            p, rel = ep.problem, ep.rel
            row: dict[str, Any] = {"problem": i, "seed": ep.seed, "ctg0": ep.ctg0, "J_REL": rel.cost}
            scp_rel = solve_scp(scenario, p, rel.X, rel.U)
            t0 = time.perf_counter()
            X, U = planner.warm_start([p], rtg0=-rel.cost, ctg0=0.0)
            t_tto = time.perf_counter() - t0
            X_tto, U_tto = X[0], U[0]
            scp_tto = solve_scp(scenario, p, X_tto, U_tto)
            for name, res, ws in (("SCP(REL)", scp_rel, ep.rel_time), ("SCP(TTO)", scp_tto, t_tto)):
                row[name] = {
                    "cost": res.cost if res.success else float("nan"),
                    "iterations": res.iterations,
                    "time": ws + res.solve_time,
                    "status": res.status.value,
                }
            trajs = {
                "REL (lower bound)": rel.X,
                "TTO rollout": X_tto,
                "SCP from REL": scp_rel.X,
                "SCP from TTO": scp_tto.X,
            }
            if not args.no_mpc:
                for provider in (RELProvider(), DISTProvider(), TTOProvider(planner)):
                    epi = run_mpc(scenario, p, provider, args.horizon, rel_cost=rel.cost)
                    row[f"{provider.name}@{args.horizon}"] = {
                        "cost": epi.cost,
                        "feasible": epi.feasible,
                        "mean_step": float(np.mean(epi.step_times)),
                        "max_step": float(np.max(epi.step_times)),
                    }
                    if provider.name == "TTO-MPC":
                        trajs[f"TTO-MPC H={args.horizon}"] = epi.X
            rows.append(row)
            plots.append((p, trajs))
    _print_table(rows)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "demo.json").write_text(
        json.dumps({"model": args.model, "scenario": scenario.name, "rows": rows}, indent=2, default=float)
    )
    _plot(scenario, plots, out / "demo.png")
    print(f"saved {out / 'demo.png'} and {out / 'demo.json'}")
    return 0


def _print_table(rows: list[dict[str, Any]]) -> None:
    methods = [k for k in rows[0] if isinstance(rows[0][k], dict)]
    print(f"\n{'problem':>7} {'ctg0':>5} {'J_REL (LB)':>11} " + " ".join(f"{m:>22}" for m in methods))
    print(f"{'':>25}" + " ".join(f"{'cost / iters|feas / s':>22}" for _ in methods))
    for r in rows:
        cells = []
        for m in methods:
            c = r[m]
            mid = c["iterations"] if "iterations" in c else ("ok" if c["feasible"] else "INF")
            t = c.get("time", c.get("mean_step"))
            cells.append(f"{c['cost']:>9.4f} /{mid!s:>4} /{t:>6.3f}")
        print(f"{r['problem']:>7} {r['ctg0']:>5} {r['J_REL']:>11.4f} " + " ".join(f"{c:>22}" for c in cells))
    print(
        "SCP columns: cost / SCP iterations / warm start + SCP seconds;"
        " MPC columns: applied cost / feasible / mean step seconds"
    )


def _plot(scenario: Any, plots: list[tuple[Any, dict[str, np.ndarray]]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(plots), figsize=(6 * len(plots), 4.5), squeeze=False)
    for ax, (problem, trajs) in zip(axes[0], plots, strict=True):
        scenario.plot(ax, problem, trajs)  # optimisation-representation states, like `ttompc solve --plot`
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
