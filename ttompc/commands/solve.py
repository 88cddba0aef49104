"""``ttompc solve [RECIPE.yaml] key=value ...``: sample a seeded problem, solve REL then SCP, print a table and
optionally plot it. Settings are ``SolveConfig`` keys; ``--scenario``/``--seed``/``--backend``/``--formulation``/
``--plot`` are shortcuts for them. Fast: imports no Lightning."""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ttompc.commands import checks
from ttompc.config import add_config_arguments, command_config, to_container
from ttompc.ranges import Checked, setting


@dataclass
class SolveConfig(Checked):
    scenario: str = "freeflyer"
    seed: int = setting(0, ge=0)  # problem seed (numpy Generator)
    backend: str = "auto"  # one of ttompc.solvers.backends.BACKEND_NAMES
    formulation: Literal["penalized", "reference"] = "penalized"
    plot: str | None = None  # PNG path for a plot of the REL and SCP trajectories


_FLAGS = ("scenario", "seed", "backend", "formulation", "plot")  # shortcut flags, dest = config key


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_config_arguments(p, "scenario=quadrotor seed=3")
    p.add_argument(
        "--scenario", help="a name (`ttompc solve --list`), module:Class or path/to/file.py:Class (default freeflyer)"
    )
    p.add_argument("--seed", type=int, help="problem seed (default 0)")
    p.add_argument("--backend", help="auto|conic|riccati|piqp|clarabel|qoco|cvxpy-naive (default auto)")
    p.add_argument("--formulation", choices=["penalized", "reference"])
    p.add_argument("--plot", metavar="PNG", help="save a plot of the REL and SCP trajectories")
    p.add_argument("--json", action="store_true", help="print the results as JSON")
    p.add_argument("--list", action="store_true", help="list the built-in and installed scenarios and exit")


def run(args: argparse.Namespace) -> int:
    from ttompc.scenarios import list_scenarios

    if args.list:
        print("\n".join(list_scenarios()))
        return 0
    cfg = command_config(SolveConfig, args, _FLAGS)
    if args.print_config:
        print(json.dumps(to_container(cfg), indent=2))
        return 0
    scenario = checks.scenario(cfg.scenario)
    checks.backend(cfg.backend)
    if cfg.plot:
        checks.figure_file(cfg.plot, "plot")
    from ttompc.solvers import solve_problem

    problem = scenario.sample(np.random.default_rng(cfg.seed))
    rel, scp = solve_problem(scenario, problem, backend=cfg.backend, formulation=cfg.formulation)
    rows = {"REL": rel, "SCP": scp}
    results: dict[str, dict[str, Any]] = {}
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
        print(json.dumps({"scenario": scenario.name, "seed": cfg.seed, "results": results}, indent=2))
    else:
        print(f"{scenario.name} (v{scenario.version}), seed {cfg.seed}, cost = Σ {scenario.cost_norm}(u)")
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
    if cfg.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7, 5))
        trajs = {name: res.X for name, res in rows.items() if res is not None}
        scenario.plot(ax, problem, trajs)
        ax.set_title(f"{scenario.name} seed {cfg.seed}")
        fig.tight_layout()
        Path(cfg.plot).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(cfg.plot, dpi=120)
        print(f"plot saved to {cfg.plot}")
    return 0 if (scp is not None and scp.success) else 1
