"""``ttompc demo [RECIPE.yaml] key=value ...``: the quickstart, offline. Load a shipped zoo model, run a few seeded
held-out non-convex problems through the evaluation protocol's per-problem steps — open loop (SCP from REL, from
the transformer (TTO) and the oracle's best optimum, ``evaluation.warmstart.evaluate_problem``) and closed loop at
one horizon on the nominal plant (every method of ``evaluation.closed_loop``) — then print the table and save
``demo.png`` (one column per problem, titled with its seed; open loop on top, closed loop below; each solution's
cost in the legend, infeasible runs marked, and the title says why REL may cross obstacles) and ``demo.json``.
``--model``, ``--problems``, ``--horizon``, ``--seed``, ``--no-mpc`` and ``--out`` are shortcuts for the
``DemoConfig`` keys."""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ttompc.commands import checks
from ttompc.config import add_config_arguments, command_config, to_container
from ttompc.errors import UserError


@dataclass
class DemoConfig:
    model: str = "freeflyer-tto-v3"  # zoo name, hf://ORG/NAME[@REV], bundle folder or .ckpt (the best free-flyer model)
    problems: int = 2
    horizon: int = 10  # MPC planning horizon H
    seed: int = 0  # root seed of the held-out evaluation stream
    mpc: bool = True  # also close the loop (slower)
    out: str = "outputs/demo"

    def __post_init__(self) -> None:
        if self.problems < 1 or self.horizon < 1:
            raise ValueError(f"problems and horizon must be >= 1, got {self.problems}, {self.horizon}")


_FLAGS = ("model", "problems", "horizon", "seed", "out")  # shortcut flags, dest = config key


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_config_arguments(p, "problems=3 horizon=20")
    p.add_argument("--model", help="zoo name, hf://ORG/NAME[@REV], bundle folder or .ckpt (default freeflyer-tto-v3)")
    p.add_argument("--problems", type=int, help="held-out problems to plan (default 2)")
    p.add_argument("--horizon", type=int, help="MPC planning horizon H (default 10)")
    p.add_argument("--seed", type=int, help="root seed of the evaluation problem stream (default 0)")
    p.add_argument("--no-mpc", action="store_true", help="open-loop warm starts only (fast); same as mpc=false")
    p.add_argument("--out", help="folder for demo.png and demo.json (default outputs/demo)")


def run(args: argparse.Namespace) -> int:
    cfg = command_config(DemoConfig, args, _FLAGS)
    if args.no_mpc:
        cfg.mpc = False
    if args.print_config:
        print(json.dumps(to_container(cfg), indent=2))
        return 0
    checks.seed(cfg.seed)
    checks.writable(cfg.out)
    from ttompc.evaluation.closed_loop import ClosedLoopConfig, episodes_per_problem, run_problem
    from ttompc.evaluation.plots import Panel, save_figure, trajectory_figure
    from ttompc.evaluation.warmstart import evaluate_problem
    from ttompc.parallel import single_torch_thread
    from ttompc.policy import Planner
    from ttompc.progress import Bar

    planner = Planner.from_pretrained(cfg.model)
    scenario = planner.scenario
    if cfg.mpc and cfg.horizon > scenario.n_steps:  # refused as `evaluate mpc` does, not clipped under its label
        raise UserError(
            f"horizon {cfg.horizon} exceeds the horizon of {scenario.name}, N = {scenario.n_steps} steps",
            f"pass --horizon {scenario.n_steps} or less (or --no-mpc)",
        )
    print(
        f"model {cfg.model}: {scenario.name} v{scenario.version}, "
        f"{sum(p.numel() for p in planner.model.parameters()) / 1e6:.2f}M parameters"
    )
    # the measurement: the problems of the evaluation stream of seed, the paper's protocol, H on the nominal plant
    loop = ClosedLoopConfig(scenario=scenario.name, problems=cfg.problems, seed=cfg.seed, horizons=[cfg.horizon],
                            plants=["nominal"])  # fmt: skip
    rows: list[dict[str, Any]] = []
    open_panels, closed_panels = [], []
    runs = cfg.problems * (1 + (episodes_per_problem(loop, models=1) if cfg.mpc else 0))  # open loop + episodes
    with single_torch_thread(), Bar(runs, "demo", "run") as bar:
        for i in range(cfg.problems):
            [ep] = loop.problem_set(scenario, [i])
            ws, trajs = evaluate_problem(scenario, ep, {"TTO": planner})
            bar.update()
            row: dict[str, Any] = {"problem": i, "seed": ep.seed, "ctg0": ep.ctg0, "J_REL": ep.rel_cost}
            for name, label in (("REL", "SCP(REL)"), ("TTO", "SCP(TTO)"), ("ORACLE", "ORACLE")):
                row[label] = {
                    "cost": ws[f"{name}_cost"],
                    "iterations": ws[f"{name}_iterations"],
                    "time": ws[f"{name}_time"],
                    "feasible": ws[f"{name}_success"],
                }
            title = f"problem {i}, seed {ep.seed} (ctg0 = {ep.ctg0})"
            failed = {f"SCP from {n}" for n in ("REL", "TTO") if not ws[f"{n}_success"]}
            costs = {"REL (lower bound)": ep.rel_cost, "ORACLE (best optimum)": ws["ORACLE_cost"]}
            costs |= {f"SCP from {n}": ws[f"{n}_cost"] for n in ("REL", "TTO") if ws[f"{n}_success"]}
            open_panels.append(Panel(ep.problem, trajs, f"open loop: {title}", failed, costs))
            if cfg.mpc:
                records, executed = run_problem(scenario, ep, {"TTO": planner}, loop, bar.update)
                for r in records:
                    row[f"{r['method']}@{cfg.horizon}"] = {
                        "cost": r["cost"],
                        "feasible": r["feasible"],
                        "mean_step": r["mean_step_time"],
                        "max_step": r["max_step_time"],
                    }
                closed = {f"{m} H={H}": X for (_, m, H), X in executed.items()}
                bad = {f"{r['method']} H={r['horizon']}" for r in records if not r["feasible"]}
                applied = {f"{r['method']} H={r['horizon']}": r["cost"] for r in records if r["feasible"]}
                closed_panels.append(Panel(ep.problem, closed, f"closed loop: {title}", bad, applied))
            rows.append(row)
    _print_table(rows)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "demo.json").write_text(
        json.dumps({"model": cfg.model, "scenario": scenario.name, "rows": rows}, indent=2, default=float)
    )
    panels = open_panels + closed_panels
    heading = (
        f"{cfg.model} on {scenario.name}. J: control cost (lower is better).\nREL: the convex relaxation without "
        "keep-out zones (a lower bound on J), so it may cross obstacles."
    )
    fig = trajectory_figure(scenario, panels, heading, rows=2 if closed_panels else 1)
    save_figure(fig, out / "demo.png")
    print(f"saved {out / 'demo.png'} and {out / 'demo.json'}")
    return 0


def _print_table(rows: list[dict[str, Any]]) -> None:
    methods = [k for k in rows[0] if isinstance(rows[0][k], dict)]
    width = max(22, *(len(m) + 1 for m in methods))
    print(f"\n{'problem':>7} {'seed':>20} {'ctg0':>5} {'J_REL (LB)':>11} " + " ".join(f"{m:>{width}}" for m in methods))
    for r in rows:
        cells = []
        for m in methods:
            c = r[m]
            mid = c["iterations"] if "iterations" in c else ("ok" if c["feasible"] else "INF")
            cost = f"{c['cost']:.4f}" if math.isfinite(c["cost"]) else "INF"
            t = c.get("time", c.get("mean_step"))
            cells.append(f"{cost:>9} /{mid!s:>4} /{t:>6.3f}")
        print(
            f"{r['problem']:>7} {r['seed']:>20} {r['ctg0']:>5} {r['J_REL']:>11.4f} "
            + " ".join(f"{c:>{width}}" for c in cells)
        )
    print(
        "open-loop columns: cost / SCP iterations / warm start + SCP seconds;"
        " MPC columns: applied cost (INF: infeasible or goal missed) / ok|INF / mean step seconds"
    )
