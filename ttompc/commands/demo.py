"""``ttompc demo [RECIPE.yaml] key=value ...``: the quickstart, offline. Two shipped zoo models on held-out non-convex
problems where what they add shows, in a table that fits 100 columns:

* warm start: the problems of the measurement ``eval`` (a ``Measurement``: the first ``eval.problems`` held-out
  non-convex problems of the evaluation stream of root seed ``eval.seed``) each run the open-loop protocol
  (``evaluation.warmstart.evaluate_problem``: SCP from REL and from ``model``'s rollout; the oracle without random
  detours). Shown: the ``problems`` whose two SCP optima differ most — by |J_SCP(model) − J_SCP(REL)| / J_REL, a
  failure on one side counting as the largest difference, then by the difference in SCP iterations, then in stream
  order — whichever side is cheaper;
* MPC, on those problems, as ``eval`` says (its one horizon, on the nominal plant, under its protocol and ``mpc``
  overrides): the robust TTO-MPC of ``mpc_model``'s model slot (``ttompc.mpc.methods``: ``evaluate mpc``'s best
  method of the recommended protocol, named as its report names it: R-FT-TTO-MPC[rtg=value] for the zoo's
  fine-tuned model with a value output) against REL-MPC, the paper's baseline, at H = ``rel_horizon`` under the
  paper's protocol: goal reached, cost above J_REL, mean step time.

A one-line summary closes the table: the scan's count of problems where the model's warm start reached a cheaper or
a costlier optimum than REL's (``SAME`` apart or more; a failed SCP counts against its side), and the MPC goals and
step-time ratio (``stats.paired``, the comparison of ``evaluate compare``). ``demo.json`` has every scanned problem
and the shown ones in full, ``demo.png`` draws the shown ones (open loop on top, closed loop below; each solution's
cost in the legend, infeasible runs marked, and the title says why REL may cross obstacles). ``--model``,
``--mpc-model``, ``--problems``, ``--horizon`` (``eval.horizons=[H]``), ``--seed`` (``eval.seed``), ``--no-mpc`` and
``--out`` are shortcuts for the ``DemoConfig`` keys."""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ttompc.config import add_config_arguments, command_config, to_container
from ttompc.errors import UserError
from ttompc.evaluation.measurement import Measurement
from ttompc.ranges import Checked, setting

if TYPE_CHECKING:
    from ttompc.evaluation.plots import Panel
    from ttompc.evaluation.problems import EvalProblem
    from ttompc.policy import Planner

SAME = 0.01  # SCP optima of one problem closer than 1% of J_REL count as the same optimum
DEMO_FILES = ("demo.json", "demo.png")  # what the demo writes into ``out``


@dataclass
class DemoConfig(Checked):
    model: str = "freeflyer-tto-v3"  # open-loop warm starts: zoo name, hf://ORG/NAME[@REV], bundle folder or .ckpt
    mpc_model: str = "freeflyer-ft-tto-v5"  # TTO-MPC: the same forms, the same scenario as model
    problems: int = setting(2, ge=1)  # shown: the scanned problems whose two warm starts differ most
    # the scan (its held-out non-convex problems, run open loop to choose the shown ones from; the zoo cards' seed)
    # and TTO-MPC's closed loop (its protocol and one horizon, on the nominal plant)
    eval: Measurement = field(
        default_factory=lambda: Measurement(protocol="recommended", problems=12, seed=4242, horizons=[10])
    )
    # REL-MPC planning horizon H (the paper's baseline, under the paper's protocol)
    rel_horizon: int = setting(30, ge=1)
    mpc: bool = True  # also close the loop (slower)
    out: str = "outputs/demo"

    def __post_init__(self) -> None:
        super().__post_init__()
        self.eval.check_single("demo.eval")
        if self.eval.plants != ["nominal"]:
            raise ValueError(f"demo.eval runs on the nominal plant, got plants={self.eval.plants}")
        if self.eval.problems < self.problems:
            raise ValueError(
                f"invalid eval.problems={self.eval.problems}: the scan must hold at least problems={self.problems}"
            )

    def rel_loop(self) -> Measurement:
        """REL-MPC's closed loop: ``eval``'s problems at H = ``rel_horizon`` under the paper's protocol."""
        return Measurement(
            protocol="paper", problems=self.eval.problems, seed=self.eval.seed, horizons=[self.rel_horizon]
        )


# shortcut flags: argparse dest -> config key
_FLAGS = {
    "model": "model",
    "mpc_model": "mpc_model",
    "problems": "problems",
    "horizon": "eval.horizons",
    "seed": "eval.seed",
    "out": "out",
}


def _one_horizon(text: str) -> str:
    """``--horizon H`` as the value of ``eval.horizons``: ``[H]``."""
    return f"[{int(text)}]"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_config_arguments(p, "problems=3 eval.problems=20 eval.horizons=[20]")
    p.add_argument(
        "--model", help="warm-start model: zoo name, hf://ORG/NAME[@REV], bundle or .ckpt (default freeflyer-tto-v3)"
    )
    p.add_argument("--mpc-model", help="TTO-MPC model, same forms (default freeflyer-ft-tto-v5)")
    p.add_argument("--problems", type=int, help="problems shown, chosen from the first eval.problems=12 (default 2)")
    p.add_argument(
        "--horizon",
        type=_one_horizon,
        help="TTO-MPC planning horizon H, eval.horizons=[H] (default 10; REL-MPC: rel_horizon=30)",
    )
    p.add_argument("--seed", type=int, help="root seed of the evaluation problem stream, eval.seed (default 4242)")
    p.add_argument("--no-mpc", action="store_true", help="open-loop warm starts only (fast); same as mpc=false")
    p.add_argument("--out", help="folder for demo.png and demo.json (default outputs/demo)")


def run(args: argparse.Namespace) -> int:
    cfg = command_config(DemoConfig, args, _FLAGS)
    if args.no_mpc:
        cfg.mpc = False
    if args.print_config:
        print(json.dumps(to_container(cfg), indent=2))
        return 0
    from ttompc.outputs import claim_folder

    # new, empty or an earlier demo's folder (demo.json, demo.png: refreshed), never a folder of other files
    claim_folder(cfg.out, "demo", lambda folder: all(p.name in DEMO_FILES for p in folder.iterdir()))
    from ttompc.evaluation.plots import save_figure, trajectory_figure
    from ttompc.policy import Planner

    planner = Planner.from_pretrained(cfg.model)
    scenario = planner.scenario
    too_long = [h for h in (cfg.eval.horizons[0], cfg.rel_horizon) if h > scenario.n_steps]
    if cfg.mpc and too_long:  # refused as `evaluate mpc` does, not clipped under its label
        raise UserError(
            f"horizon {too_long[0]} exceeds the horizon of {scenario.name}, N = {scenario.n_steps} steps",
            f"pass eval.horizons and rel_horizon of {scenario.n_steps} or less (or --no-mpc)",
        )
    mpc_planner = Planner.from_pretrained(cfg.mpc_model) if cfg.mpc else None
    if mpc_planner is not None and mpc_planner.scenario.name != scenario.name:
        raise UserError(
            f"mpc_model {cfg.mpc_model} plans {mpc_planner.scenario.name}, model {cfg.model} plans {scenario.name}",
            f"pass --mpc-model with a {scenario.name} model (`ttompc zoo list`), or --no-mpc",
        )
    scanned, rows, panels, chosen = _open_loop(cfg, planner)
    mpc: tuple[str, str] | None = None  # the two methods' columns, model's first
    if mpc_planner is not None:
        mpc, closed = _closed_loop(cfg, mpc_planner, chosen, rows)
        panels += closed
    print("\n".join(_table(cfg, scenario.name, scanned, rows, mpc)))
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    report = {"config": to_container(cfg), "scenario": scenario.name, "scanned": scanned, "rows": rows}
    (out / DEMO_FILES[0]).write_text(json.dumps(report, indent=2, default=float))
    heading = (
        f"{cfg.model} (warm starts)" + (f" and {cfg.mpc_model} (MPC)" if cfg.mpc else "") + f" on {scenario.name}. "
        "J: control cost (lower is better).\nREL: the convex relaxation without keep-out zones (a lower bound on J), "
        "so it may cross obstacles."
    )
    fig = trajectory_figure(scenario, panels, heading, rows=2 if mpc is not None else 1)
    save_figure(fig, out / DEMO_FILES[1])
    print(f"saved {out / DEMO_FILES[1]} and {out / DEMO_FILES[0]}")
    return 0


def _open_loop(
    cfg: DemoConfig, planner: Planner
) -> tuple[list[dict[str, Any]], list[dict[str, Any]], list[Panel], list[EvalProblem]]:
    """The scan: every problem of ``cfg.eval`` run open loop (``evaluate_problem``); returns the scanned rows, the rows
    and panels of the ``cfg.problems`` chosen ones (module doc) and those problems, in stream order."""
    from ttompc.evaluation.plots import Panel
    from ttompc.evaluation.warmstart import evaluate_problem
    from ttompc.parallel import single_torch_thread
    from ttompc.progress import Bar

    scenario = planner.scenario
    found = []  # (problem, its open-loop row, trajectories) of every scanned problem
    with single_torch_thread(), Bar(cfg.eval.problems, "demo: warm starts", "problem") as bar:
        for ep in cfg.eval.problem_set(scenario):
            found.append(
                (
                    ep,
                    *evaluate_problem(
                        scenario, ep, {"TTO": planner}, oracle_detours=0, backend=cfg.eval.settings.backend
                    ),
                )
            )
            bar.update()
    chosen = sorted(sorted(found, key=lambda f: _difference(f[1]))[: cfg.problems], key=lambda f: f[0].index)
    rows: list[dict[str, Any]] = []
    panels = []
    for ep, ws, trajs in chosen:
        row: dict[str, Any] = {"problem": ep.index, "seed": ep.seed, "ctg0": ep.ctg0, "J_REL": ep.rel_cost}
        for name, label in (("REL", "SCP(REL)"), ("TTO", "SCP(TTO)"), ("ORACLE", "ORACLE")):
            row[label] = {
                "cost": ws[f"{name}_cost"],
                "iterations": ws[f"{name}_iterations"],
                "time": ws[f"{name}_time"],
                "feasible": ws[f"{name}_success"],
            }
        rows.append(row)
        failed = {f"SCP from {n}" for n in ("REL", "TTO") if not ws[f"{n}_success"]}
        costs = {"REL (lower bound)": ep.rel_cost, "ORACLE (best optimum)": ws["ORACLE_cost"]}
        costs |= {f"SCP from {n}": ws[f"{n}_cost"] for n in ("REL", "TTO") if ws[f"{n}_success"]}
        title = f"open loop: {_title(ep.index, cfg.eval.seed, ep.ctg0)}"
        panels.append(Panel(ep.problem, trajs, title, failed, costs))
    return [ws for _, ws, _ in found], rows, panels, [ep for ep, _, _ in chosen]


def _closed_loop(
    cfg: DemoConfig, planner: Planner, eps: list[EvalProblem], rows: list[dict[str, Any]]
) -> tuple[tuple[str, str], list[Panel]]:
    """The robust TTO-MPC of ``planner``'s model slot under ``cfg.eval`` and REL-MPC under ``cfg.rel_loop()`` on the
    chosen problems ``eps``, both from ``ttompc.mpc.methods``: each episode's numbers into its problem's row (under
    "METHOD@H"); returns the two methods' keys (the model's first) and one panel per problem."""
    from ttompc.evaluation.episodes import episode_record
    from ttompc.evaluation.plots import Panel
    from ttompc.model_slots import slot_of
    from ttompc.mpc.loop import run_mpc_batch
    from ttompc.mpc.methods import BASELINE, METHODS, MethodInputs, model_method
    from ttompc.parallel import single_torch_thread
    from ttompc.progress import Bar

    scenario = planner.scenario
    learned = model_method(slot_of(planner.extra), robust=True)
    methods = [(learned, cfg.eval, planner), (METHODS[BASELINE], cfg.rel_loop(), None)]
    starts = [ep.start for ep in eps]
    episodes = []
    with single_torch_thread(), Bar(len(methods) * len(eps), "demo: MPC", "episode") as bar:

        def tick() -> None:  # one lockstep step of every episode
            bar.update(len(eps) / scenario.n_steps)

        for method, loop, model in methods:
            [(_, run)] = loop.runs(scenario)
            providers = method.providers(MethodInputs(loop.settings, [None] * len(eps), model))
            episodes += run_mpc_batch(scenario, starts, providers, run, tick)
    keys = [f"{e.method}@{e.horizon}" for e in episodes[:: len(eps)]]
    panels = []
    for i, (ep, row) in enumerate(zip(eps, rows, strict=True)):
        closed, bad, applied = {}, set(), {}
        for e in episodes[i :: len(eps)]:
            r = episode_record(e)
            key = f"{e.method}@{e.horizon}"
            row[key] = {k: r[k] for k in ("cost", "rel_increment", "feasible", "terminal_error")}
            row[key] |= {"mean_step": r["mean_step_time"], "max_step": r["max_step_time"]}
            label = f"{e.method} H={e.horizon}"
            closed[label] = e.X
            if e.feasible:
                applied[label] = e.cost
            else:
                bad.add(label)
        title = f"closed loop: {_title(ep.index, cfg.eval.seed, ep.ctg0)}"
        panels.append(Panel(ep.problem, closed, title, bad, applied))
    return (keys[0], keys[1]), panels


def _title(index: int, seed: int, ctg0: int) -> str:
    return f"problem #{index} of root seed {seed} (ctg0 = {ctg0})"


def _gap(ws: dict[str, Any]) -> float:
    """(J_SCP(model) − J_SCP(REL)) / J_REL of an open-loop row: −inf when only SCP from REL failed, +inf when only
    SCP from the model did, nan when both did."""
    rel, tto = ws["REL_success"], ws["TTO_success"]
    if rel and tto:
        return float((ws["TTO_cost"] - ws["REL_cost"]) / ws["rel_cost"])
    return math.nan if rel == tto else (math.inf if rel else -math.inf)


def _difference(ws: dict[str, Any]) -> tuple[float, int, int]:
    """Sort key, most different first: −|``_gap``| (0 when both runs failed), −|difference of their SCP
    iterations|, the problem's index."""
    gap = _gap(ws)
    return -abs(gap) if not math.isnan(gap) else 0.0, -abs(ws["TTO_iterations"] - ws["REL_iterations"]), ws["problem"]


def _above(cost: float, rel_cost: float, ok: bool) -> str:
    """Cost above J_REL in percent ("failed" when the run failed or missed its goal)."""
    return f"{100 * (cost - rel_cost) / rel_cost:+.1f}%" if ok and math.isfinite(cost) else "failed"


def _table(
    cfg: DemoConfig,
    scenario: str,
    scanned: Sequence[dict[str, Any]],
    rows: Sequence[dict[str, Any]],
    mpc: tuple[str, str] | None,
) -> list[str]:
    """The printed result, no line wider than 100 columns for zoo models: a header naming the problems, the
    warm-start table, the MPC table (``mpc``: its two methods' keys in ``rows``, model first; None: left out) and
    the summary line."""
    n = len(rows)
    lines = [
        f"{scenario}, problem #i: held-out non-convex problem i of root seed {cfg.eval.seed}. Shown: the {n} of",
        f"#0-#{cfg.eval.problems - 1} where the two warm starts differ most. Cost: J above J_REL, REL's lower bound.",
        "",
        f"warm start: full-horizon SCP from REL and from {cfg.model} (time: warm start + SCP)",
        f"{'':20}  |  {'SCP from REL':<22}  |  SCP from the model",
        f"{'problem':>7} {'ctg0':>4} {'J_REL':>7}  |  {'cost':>8} {'iters':>5} {'time':>7}  |  "
        f"{'cost':>8} {'iters':>5} {'time':>7}",
    ]
    for r in rows:
        cells = [f"{'#' + str(r['problem']):>7} {r['ctg0']:>4} {r['J_REL']:>7.4f}"]
        for c in (r["SCP(REL)"], r["SCP(TTO)"]):
            cells.append(f"{_above(c['cost'], r['J_REL'], c['feasible']):>8} {c['iterations']:>5} {c['time']:>6.2f}s")
        lines.append("  |  ".join(cells))
    gaps = [_gap(s) for s in scanned]
    cheaper, costlier = sum(g <= -SAME for g in gaps), sum(g >= SAME for g in gaps)  # nan: neither
    summary = f"summary: warm start beats REL on {cheaper}/{len(scanned)}, loses on {costlier}"
    if mpc is not None:
        from ttompc.evaluation.closed_loop_report import protocol_label
        from ttompc.evaluation.stats import Outcome, paired

        width = max(23, *(len(k) for k in mpc))
        lines += [
            "",
            f"MPC, nominal plant: {cfg.mpc_model} under protocol={protocol_label(cfg.eval)}, REL-MPC under paper",
            f"{'':7}  |  {mpc[0]:<{width}}  |  {mpc[1]:<{width}}  |",
            f"{'problem':>7}  |  {'goal':<{width - 19}} {'cost':>8} {'step':>9}  |  "
            f"{'goal':<{width - 19}} {'cost':>8} {'step':>9}  |  step-time ratio",
        ]
        for r in rows:
            cells = [f"{'#' + str(r['problem']):>7}"]
            for c in (r[k] for k in mpc):
                goal = "yes" if c["feasible"] else "no"
                cost = _above(c["cost"], r["J_REL"], c["feasible"])
                cells.append(f"{goal:<{width - 19}} {cost:>8} {1e3 * c['mean_step']:>7.1f}ms")
            cells.append(f"{r[mpc[1]]['mean_step'] / r[mpc[0]]['mean_step']:>14.1f}×")
            lines.append("  |  ".join(cells))
        model, rel = (
            {r["problem"]: Outcome(r[k]["feasible"], r[k]["rel_increment"], r[k]["mean_step"]) for r in rows}
            for k in mpc
        )
        pair = paired(rel, model)
        summary += (
            f"; MPC goals {pair['other_goals']}/{n} vs REL-MPC {pair['base_goals']}/{n}, "
            f"{pair['step_ratio']:.1f}× faster steps"
        )
        lines.append("goal: reached, every constraint met; step: mean time per MPC step (observe + warm start + solve)")
    return [*lines, "", summary]
