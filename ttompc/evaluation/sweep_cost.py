"""What a closed-loop sweep (``ttompc evaluate mpc`` over several horizons, ``make figures``) costs: measured per
episode on a tiny run, then planned for a budget of CPU-hours before the sweep starts (``docs/evaluation.md``).

* ``measure``: for ``problems`` (say 2) held-out problems of a ``ClosedLoopConfig``, in this process on one thread,
  the CPU seconds (``time.process_time``) of building a problem and its full-horizon plan (``problem_s``: the cheapest
  problem's, as the first pays one-off compilation; a merged entry keeps the smaller of its runs'), and of one
  episode of each method at each measured horizon on each plant (``episode_s[method][plant][H]``), the episodes of a
  method run in lockstep as the sweep runs them. Each method first runs two untimed steps (compilation, solver
  structures). The entry records the machine and its load: on a loaded machine CPU seconds grow less than wall
  seconds, but grow.
* ``sweep_hours``: the CPU-hours of a sweep on ``problems`` problems, the given horizons and plants: per problem its
  ``problem_s`` plus every measured method's episode at each H and plant, H between measured horizons interpolated
  linearly (beyond them, the nearest two extrapolated); a plant that was not measured costs what ``nominal`` did.
  The sweep runs lockstep batches of ``batch`` = 10 problems: batched rollouts make its model methods' episodes
  cheaper than the measurement's smaller batch, so the estimate errs high.
* ``plan``: for a budget of CPU-hours per scenario, the paper's grid when it affords ``MIN_PROBLEMS``, else the
  reduced grid (the shape of both figures before the problem count), with as many problems as the budget buys up to
  ``MAX_PROBLEMS``; the minimal grid only when the reduced one does not buy two problems.

The measurements live in one JSON file (``COST_FILE``), one entry per scenario, each written by ``measure`` with its
command lines (a second run on more horizons adds to the first, ``merge``). The command line (``main``):
``python -m ttompc.evaluation.sweep_cost measure|estimate|plan``; ``make figures`` runs ``estimate`` before each
sweep ("about N CPU-hours"), ``make figures-plan`` runs ``plan``.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ttompc.errors import UserError
from ttompc.evaluation.closed_loop import ClosedLoopConfig, model_sources
from ttompc.evaluation.machine import cpu_model, load_average, machine_label, machine_record
from ttompc.evaluation.metrics import write_json

COST_FILE = Path("docs/sweep-cost.json")
# the horizon grids of ``make figures`` (FIG_GRID), poorest first: the equal-cost table's two horizons, the reduced
# grid (the shape of both figures at a fifth of the paper's cost when H = 100 dominates) and the paper's Fig. 5/6
GRIDS = {"minimal": [10, 30], "reduced": [10, 20, 30, 50, 100], "paper": list(range(10, 101, 10))}
MIN_PROBLEMS, MAX_PROBLEMS = 100, 500  # the floor and the paper's count per scenario
SAME = ("problems", "seed", "protocol", "models")  # what two measurements of a scenario share to be merged (``merge``)


def measure(cfg: ClosedLoopConfig) -> dict[str, Any]:
    """The cost entry of ``cfg``'s scenario (module doc): ``problem_s``, ``episode_s`` and the run's settings and
    machine. ``cfg.scenario`` must be set."""
    import torch

    from ttompc.mpc.loop import MPCRun, run_mpc_batch
    from ttompc.mpc.methods import MethodInputs, methods_for
    from ttompc.mpc.providers import full_horizon_plan
    from ttompc.policy import Planner
    from ttompc.scenarios import get_scenario

    if cfg.scenario is None:
        raise ValueError("ClosedLoopConfig.scenario is not set")
    torch.set_num_threads(1)  # one core, as each worker of the sweep's pool runs
    load = load_average()
    sc, s = get_scenario(cfg.scenario), cfg.settings
    models = {slot: Planner.from_pretrained(src, sc, device=cfg.device) for slot, src in model_sources(cfg).items()}
    eps, plans, seconds = [], [], []
    for index in range(cfg.problems):
        t = time.process_time()
        (ep,) = cfg.problem_set(sc, [index])
        plans.append(full_horizon_plan(sc, ep.problem, s.backend))
        eps.append(ep)
        seconds.append(time.process_time() - t)
    problem_s = min(seconds)  # the first problem pays one-off compilation (solver kernels), a sweep's worker once
    starts = [ep.start for ep in eps]
    methods = methods_for(models, cfg.robust_blend)

    def inputs(method: Any, n: int) -> Any:
        model = models.get(method.model or "")
        return MethodInputs(s, plans[:n], model, cfg.robust_blend, cfg.rtg_scale)

    for method in methods:  # untimed: compilation and the first solver structures
        run_mpc_batch(sc, starts[:1], method.providers(inputs(method, 1)), MPCRun(min(cfg.horizons), s, 2))
    episode_s: dict[str, dict[str, dict[str, float]]] = {}
    for plant, run in cfg.runs(sc):
        for method in methods:
            t = time.process_time()
            run_mpc_batch(sc, starts, method.providers(inputs(method, len(eps))), run)
            cell = episode_s.setdefault(method.name, {}).setdefault(plant, {})
            cell[str(run.horizon)] = round((time.process_time() - t) / len(eps), 4)
    return {
        "problems": cfg.problems,
        "seed": cfg.seed,
        "protocol": cfg.protocol,
        "models": model_sources(cfg),
        "problem_s": round(problem_s, 4),
        "episode_s": episode_s,
        "machine": machine_record(load),
    }


def episode_seconds(entry: dict[str, Any], method: str, plant: str, horizon: int) -> float:
    """The CPU seconds of one episode of ``method`` at ``horizon`` on ``plant`` by ``entry`` (module doc:
    interpolated between measured horizons, ``nominal``'s for an unmeasured plant)."""
    by_plant = entry["episode_s"][method]
    points = sorted((int(h), s) for h, s in by_plant.get(plant, by_plant["nominal"]).items())
    if len(points) == 1:
        return float(points[0][1])
    i = next((k for k in range(1, len(points) - 1) if horizon <= points[k][0]), len(points) - 1)
    (h0, s0), (h1, s1) = points[i - 1], points[i]
    return max(0.0, s0 + (s1 - s0) * (horizon - h0) / (h1 - h0))


def sweep_hours(entry: dict[str, Any], problems: int, horizons: Sequence[int], plants: Sequence[str]) -> float:
    """The CPU-hours of a sweep of ``problems`` problems over ``horizons`` and ``plants`` with every method of
    ``entry`` (module doc)."""
    per_problem = entry["problem_s"] + sum(
        episode_seconds(entry, m, p, h) for m in entry["episode_s"] for p in plants for h in horizons
    )
    return problems * per_problem / 3600


def plan(entry: dict[str, Any], budget_h: float, plants: Sequence[str]) -> dict[str, Any]:
    """The sweep ``budget_h`` CPU-hours buy (module doc): ``grid`` (a ``GRIDS`` name), ``problems`` and ``hours``;
    ``problems`` 0 when the budget does not buy one problem on the minimal grid."""
    per_problem = {name: sweep_hours(entry, 1, grid, plants) for name, grid in GRIDS.items()}
    if budget_h >= MIN_PROBLEMS * per_problem["paper"]:
        name = "paper"
    else:
        name = "reduced" if budget_h >= 2 * per_problem["reduced"] else "minimal"
    problems = min(MAX_PROBLEMS, int(budget_h / per_problem[name]))
    return {"grid": name, "problems": problems, "hours": problems * per_problem[name]}


def read_costs(path: str | Path) -> dict[str, Any]:
    """The cost file at ``path``: its entries by scenario; raises ``UserError`` for a missing or unreadable file."""
    path = Path(path)
    hint = "measure them: python -m ttompc.evaluation.sweep_cost measure model=M ft_model=F problems=2"
    try:
        costs = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UserError(f"no sweep costs at {path}", hint) from None
    except (OSError, UnicodeDecodeError, ValueError) as err:
        raise UserError(f"{path} is not a sweep-cost file ({err})", hint) from err
    if not isinstance(costs, dict) or not all(isinstance(e, dict) and "episode_s" in e for e in costs.values()):
        raise UserError(f"{path} is not a sweep-cost file (entries by scenario, each with its episode_s)", hint)
    return costs


def _entry(costs: dict[str, Any], scenario: str, path: str | Path) -> dict[str, Any]:
    if scenario not in costs:
        raise UserError(
            f"{path} holds no costs of {scenario} (it has {', '.join(sorted(costs)) or 'none'})",
            f"measure them: python -m ttompc.evaluation.sweep_cost measure scenario={scenario} ...",
        )
    return dict(costs[scenario])


def _ints(text: str) -> list[int]:
    """'[10,20]' or '10,20' as a list of positive integers (``argparse`` type)."""
    try:
        values = [int(x) for x in text.strip("[]").split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected integers like [10,20,30], got {text!r}") from None
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers like [10,20,30], got {text!r}")
    return values


def _names(text: str) -> list[str]:
    return [x.strip() for x in text.strip("[]").split(",") if x.strip()]


def _estimate(args: argparse.Namespace) -> str:
    costs = read_costs(args.costs)
    entry = _entry(costs, args.scenario, args.costs)
    hours = sweep_hours(entry, args.problems, args.horizons, args.plants)
    here = "this machine" if entry["machine"]["cpu"] == cpu_model() else f"a {entry['machine']['cpu']}"
    return (
        f"{args.scenario}: {args.problems} problems x H = {args.horizons} x {args.plants}: about {hours:.1f} CPU-hours "
        f"on {here} ({hours / args.workers:.1f} h on {args.workers} idle cores; costs of {args.costs}, measured at "
        f"load {entry['machine']['load_average'][2]:.1f})"
    )


def _plan(args: argparse.Namespace) -> str:
    costs = read_costs(args.costs)
    lines = [
        f"| scenario | {' | '.join(f'{g} ×{n}' for g in GRIDS for n in (MIN_PROBLEMS, MAX_PROBLEMS))} "
        f"| {args.budget:g} CPU-h buy |",
        "|---|" + "---|" * (2 * len(GRIDS) + 1),
    ]
    for scenario in sorted(costs):
        entry = costs[scenario]
        cells = [
            f"{sweep_hours(entry, n, grid, args.plants):.1f}"
            for grid in GRIDS.values()
            for n in (MIN_PROBLEMS, MAX_PROBLEMS)
        ]
        p = plan(entry, args.budget, args.plants)
        buy = f"FIG_GRID={p['grid']} FIG_PROBLEMS={p['problems']} ({p['hours']:.1f} h)" if p["problems"] else "–"
        lines.append(f"| {scenario} | {' | '.join(cells)} | {buy} |")
    machines = sorted({machine_label(e["machine"]) for e in costs.values()})
    grids = "; ".join(f"{name} H = {', '.join(map(str, grid))}" for name, grid in GRIDS.items())
    lines.append(
        f"\nCPU-hours per scenario on the {' and '.join(args.plants)} plants, every method; grids: {grids}; "
        f"measured on {'; '.join(machines)} ({args.costs}). Wall hours: divide by the idle cores (workers=)."
    )
    return "\n".join(lines)


def _measure(args: argparse.Namespace) -> str:
    from ttompc.config import command_config
    from ttompc.policy import Planner

    cfg = command_config(ClosedLoopConfig, args)
    sources = list(model_sources(cfg).values())
    if cfg.scenario is None:
        if not sources:
            raise UserError("measure needs a model or a scenario", "pass model=NAME ft_model=NAME or scenario=NAME")
        cfg.scenario = Planner.from_pretrained(sources[0]).scenario.name
    costs = read_costs(args.costs) if Path(args.costs).is_file() else {}
    command = shlex.join(["python", "-m", "ttompc.evaluation.sweep_cost", "measure", *args.settings])
    costs[cfg.scenario] = merge(costs.get(cfg.scenario), {**measure(cfg), "commands": [command]})
    write_json(Path(args.costs), costs)
    return f"{cfg.scenario}: costs written to {args.costs}"


def merge(old: dict[str, Any] | None, new: dict[str, Any]) -> dict[str, Any]:
    """``new``, a scenario's measured entry, with the cells (method, plant, H) of ``old`` it did not measure when
    both measured the same ``SAME`` settings (more horizons measured by a second run), else ``new`` alone; the
    entry's ``commands`` are those of every run in it, its ``problem_s`` the smaller one."""
    if old is None or any(old.get(key) != new[key] for key in SAME):
        return new
    cells = {m: {p: dict(hs) for p, hs in by_plant.items()} for m, by_plant in old["episode_s"].items()}
    for method, by_plant in new["episode_s"].items():
        for plant, hs in by_plant.items():
            cells.setdefault(method, {}).setdefault(plant, {}).update(hs)
    commands = [*old.get("commands", []), *new["commands"]]
    return {**new, "problem_s": min(old["problem_s"], new["problem_s"]), "episode_s": cells, "commands": commands}


def main(argv: Sequence[str] | None = None) -> int:
    """The command line of the module doc; prints its result (a ``UserError`` as one line, exit 2)."""
    p = argparse.ArgumentParser(prog="python -m ttompc.evaluation.sweep_cost", description=__doc__.split("\n\n")[0])
    p.add_argument("--costs", default=str(COST_FILE), help=f"the sweep-cost file (default {COST_FILE})")
    sub = p.add_subparsers(dest="action", required=True)
    m = sub.add_parser("measure", help="measure one scenario's costs (ClosedLoopConfig key=value settings)")
    m.add_argument("settings", nargs="*", help="e.g. model=freeflyer-tto-v3 problems=2 horizons=[10,20,50,100]")
    e = sub.add_parser("estimate", help="the CPU-hours of one sweep")
    e.add_argument("--scenario", required=True)
    e.add_argument("--problems", type=int, required=True)
    e.add_argument("--horizons", type=_ints, required=True, help="e.g. [10,20,30,50,100]")
    e.add_argument("--workers", type=int, default=2, help="cores the sweep runs on (default 2)")
    for q in (e, sub.add_parser("plan", help="the CPU-hours of each grid, and what a budget buys")):
        q.add_argument("--plants", type=_names, default=["nominal", "perturbed"], help="default [nominal,perturbed]")
    sub.choices["plan"].add_argument("--budget", type=float, default=3.0, help="CPU-hours per scenario (default 3)")
    args = p.parse_args(argv)
    try:
        print({"measure": _measure, "estimate": _estimate, "plan": _plan}[args.action](args))
    except UserError as err:
        print(f"{p.prog}: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
