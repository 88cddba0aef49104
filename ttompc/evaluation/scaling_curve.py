"""The closed-loop learning curve over model size, data and optimiser steps (issue "zoo v4"): each point is a trained
planner, measured on fixed selection problems as the zoo's headline compares it — the learned MPC at H = 10 under
``protocol=recommended`` (R-TTO-MPC with a value output, ``robust_blend`` 0.95) against REL-MPC at H = 30 under
``protocol=paper`` — paired per problem over the problems both reach, goals counted apart, nominal and perturbed.

Each point records what it cost (parameters, problems trained on, optimiser steps, training CPU-hours) so the figure
can put every point on a compute axis. The REL-MPC@30 baseline is solved once per (plant, problems, seed) and kept in
the curve file; points already measured are skipped (resumable; a curve file holds one selection set).

    python -m ttompc.evaluation.scaling_curve measure CURVE.json --planner DIR --label L --data-problems 100000 \\
        --cpu-hours 2.1 [--problems 50 --seed 1001]
    python -m ttompc.evaluation.scaling_curve figure CURVE.json [...] --out docs/figures/scaling_closed_loop.png
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ttompc.data.shards import atomic_write_json
from ttompc.errors import UserError
from ttompc.evaluation.stats import paired_points

if TYPE_CHECKING:
    from ttompc.evaluation.measurement import Measurement
    from ttompc.evaluation.problems import EvalProblem
    from ttompc.policy import Planner

PLANTS = ("nominal", "perturbed")
BLEND = 0.95  # the robust target's blend (ttompc.mpc.methods.ROBUST_BLEND), the headline's method


@dataclass(frozen=True)
class Selection:
    """The fixed problems every point meets: ``problems`` of the evaluation stream of ``seed`` (held out from data
    generation), the learned method's ``horizon`` and the baseline's ``baseline_horizon``."""

    problems: int = 50
    seed: int = 1001
    horizon: int = 10
    baseline_horizon: int = 30
    max_steps: int | None = None  # shorter episodes, for smoke runs

    def measurement(self, plant: str, learned: bool) -> Measurement:
        from ttompc.evaluation.measurement import Measurement

        return Measurement(
            protocol="recommended" if learned else "paper",
            problems=self.problems,
            seed=self.seed,
            horizons=[self.horizon if learned else self.baseline_horizon],
            plants=[plant],
            max_steps=self.max_steps,
            robust_blend=BLEND if learned else 0.0,
        )


def _increments(episodes: Sequence[Any]) -> list[float | None]:
    """Each episode's (J − J_REL)/J_REL (``rel_increment``), None where it has none (infeasible, no J_REL)."""
    from ttompc.mpc.episode import rel_increment

    incs = [rel_increment(e.cost, e.rel_cost, e.feasible) for e in episodes]
    return [None if np.isnan(v) else v for v in incs]


def baseline_increments(scenario: Any, m: Measurement, problems: Sequence[EvalProblem]) -> list[float | None]:
    """REL-MPC's per-problem (J − J_REL)/J_REL (None where it missed the goal) under the single-run measurement."""
    from ttompc.mpc.loop import run_mpc_batch
    from ttompc.mpc.methods import BASELINE, METHODS, MethodInputs
    from ttompc.parallel import single_torch_thread

    [(_, run)] = m.runs(scenario)
    provs = METHODS[BASELINE].providers(MethodInputs(m.settings, [None] * len(problems)))
    with single_torch_thread():
        return _increments(run_mpc_batch(scenario, [p.start for p in problems], provs, run))


def planner_meta(planner: Planner, planner_dir: Path) -> dict[str, Any]:
    """What the point is: architecture, parameters (the policy's; the value output apart) and optimiser steps."""
    cfg = json.loads((planner_dir / "config.json").read_text())
    model = planner.model
    value = sum(p.numel() for n, p in model.named_parameters() if n.startswith("value_head."))
    arch = cfg["model"]
    return {
        "n_embd": arch["n_embd"],
        "n_layer": arch["n_layer"],
        "layout": arch.get("layout", "interleaved"),
        "params": sum(p.numel() for p in model.parameters()) - value,
        "value_params": value,
        "steps": int(cfg.get("extra", {}).get("global_step", 0)),
        "scenario": cfg["scenario"]["name"],
    }


def measure_point(
    curve: Path,
    planner_dir: Path,
    label: str,
    sel: Selection,
    *,
    data_problems: int,
    cpu_hours: float,
    plants: Sequence[str] = PLANTS,
    note: str = "",
    dagger_iterations: int = 0,
) -> dict[str, Any]:
    """Measure the planner at ``planner_dir`` as point ``label`` of ``curve`` (skipped when already there) and
    return its record. A curve file holds one selection; a planner of another scenario is refused."""
    from ttompc.evaluation.episodes import closed_loop_metrics
    from ttompc.parallel import single_torch_thread
    from ttompc.policy import Planner

    state: dict[str, Any] = json.loads(curve.read_text()) if curve.is_file() else {}
    if state and state.get("selection") != sel.__dict__:
        raise UserError(f"{curve} holds a curve on another selection {state.get('selection')}", "use another file")
    state.setdefault("selection", sel.__dict__)
    points: list[dict[str, Any]] = state.setdefault("points", [])
    for p in points:
        if p["label"] == label:
            return p
    planner = Planner.from_pretrained(planner_dir)
    meta = planner_meta(planner, planner_dir)
    if state.setdefault("scenario", meta["scenario"]) != meta["scenario"]:
        raise UserError(f"{planner_dir} plans {meta['scenario']}, {curve} is a {state['scenario']} curve")
    record: dict[str, Any] = {
        "label": label,
        "planner": str(planner_dir),
        **meta,
        "data_problems": data_problems,
        "cpu_hours": cpu_hours,
        "dagger_iterations": dagger_iterations,
        "note": note,
    }
    base = state.setdefault("baseline", {})
    for plant in plants:
        learned = sel.measurement(plant, learned=True)
        problems = learned.problem_set(planner.scenario)
        if plant not in base:
            base[plant] = baseline_increments(planner.scenario, sel.measurement(plant, False), problems)
            atomic_write_json(curve, state)
        with single_torch_thread():
            metrics, episodes = closed_loop_metrics(planner, learned, problems)
        inc = _increments(episodes)
        record[plant] = {
            "increments": inc,
            "step_time_mean": metrics["step_time_mean"],
            "vs_baseline": paired_points(inc, base[plant]),
        }
    points.append(record)
    atomic_write_json(curve, state)
    return record


def curve_figure(curves: Sequence[Path], out: Path) -> Path:
    """One row per curve file (a scenario each): the learned MPC@H paired against REL-MPC@30 (points of J_REL,
    ± one standard error) against training CPU-hours, nominal and perturbed, a line per model size, the marker's
    fill the data (open: fewer problems than the curve's largest set), its shape the training (circle: open-loop
    only, square: with DAgger), and the goals reached (circle: nominal, triangle: perturbed)."""
    from ttompc.evaluation.plots import row_figure

    footer = "python -m ttompc.evaluation.scaling_curve figure " + " ".join(map(str, curves))
    return row_figure(curves, _curve_row, out, size=(14, 3.8), footer=footer)


def _curve_row(path: Path, axes: Sequence[Any]) -> None:
    """The three panels of ``curve_figure`` of one curve file."""
    from matplotlib.ticker import ScalarFormatter

    state = json.loads(path.read_text())
    sel, pts = state["selection"], state["points"]
    most = max((p["data_problems"] for p in pts), default=0)
    sizes = sorted({(p["n_embd"], p["n_layer"], p["params"]) for p in pts}, key=lambda s: s[2])
    for k, (width, depth, params) in enumerate(sizes):
        mine = sorted((p for p in pts if (p["n_embd"], p["n_layer"]) == (width, depth)), key=lambda p: p["cpu_hours"])
        color = f"C{k}"
        name = f"{width}×{depth} ({params / 1e6:.1f}M)"
        for ax, plant in zip(axes[:2], PLANTS, strict=True):
            done = [p for p in mine if plant in p]
            x = [max(p["cpu_hours"], 1e-2) for p in done]
            y = [100 * p[plant]["vs_baseline"]["mean"] for p in done]
            e = [100 * np.nan_to_num(p[plant]["vs_baseline"]["se"]) for p in done]
            ax.errorbar(x, y, yerr=e, color=color, capsize=3, lw=1, label=name)
            for xi, yi, p in zip(x, y, done, strict=True):
                shape = "s" if p.get("dagger_iterations", 0) else "o"
                ax.plot(xi, yi, shape, color=color, mfc=color if p["data_problems"] >= most else "white")
        for p in mine:
            for plant, shape in zip(PLANTS, "o^", strict=True):
                if plant in p:
                    axes[2].plot(max(p["cpu_hours"], 1e-2), p[plant]["vs_baseline"]["goals"], shape, color=color)
    base_goals = {pl: sum(v is not None for v in state["baseline"].get(pl, [])) for pl in PLANTS}
    for ax, plant in zip(axes[:2], PLANTS, strict=True):
        ax.axhline(0, color="k", lw=0.6)
        ax.set_title(
            f"{state['scenario']}, {plant}: learned@{sel['horizon']} − REL-MPC@{sel['baseline_horizon']}"
            " (points of J_REL)",
            fontsize=9,
        )
    for plant, style in zip(PLANTS, ("--", ":"), strict=True):
        axes[2].axhline(base_goals[plant], color="k", lw=0.6, ls=style, label=f"REL-MPC@30, {plant}")
    axes[2].set_title(f"{state['scenario']}: goals reached of {sel['problems']} (○ nominal, △ perturbed)", fontsize=9)
    for ax in axes:
        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.xaxis.set_minor_formatter(ScalarFormatter())
        ax.set_xlabel("training CPU-hours (open marker: fewer problems)")
        ax.legend(fontsize=7)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m ttompc.evaluation.scaling_curve", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="action", required=True)
    m = sub.add_parser("measure", help="measure one planner as a point of a curve file")
    m.add_argument("curve", type=Path)
    m.add_argument("--planner", type=Path, required=True, help="a planner bundle folder")
    m.add_argument("--label", required=True)
    m.add_argument("--data-problems", type=int, required=True, help="problems of the data it was trained on")
    m.add_argument("--cpu-hours", type=float, required=True, help="training CPU-hours to reach it")
    m.add_argument("--note", default="")
    m.add_argument("--dagger-iterations", type=int, default=0, help="DAgger iterations in its training (0: none)")
    m.add_argument("--problems", type=int, default=50)
    m.add_argument("--seed", type=int, default=1001)
    m.add_argument("--horizon", type=int, default=10)
    m.add_argument("--plants", nargs="+", default=list(PLANTS), choices=PLANTS)
    m.add_argument("--max-steps", type=int, default=None)
    f = sub.add_parser("figure", help="draw curve files, one row each")
    f.add_argument("curves", type=Path, nargs="+")
    f.add_argument("--out", type=Path, default=Path("docs/figures/scaling_closed_loop.png"))
    a = p.parse_args(argv)
    if a.action == "figure":
        print(curve_figure(a.curves, a.out))
        return 0
    sel = Selection(a.problems, a.seed, a.horizon, max_steps=a.max_steps)
    r = measure_point(
        a.curve,
        a.planner,
        a.label,
        sel,
        data_problems=a.data_problems,
        cpu_hours=a.cpu_hours,
        plants=a.plants,
        note=a.note,
        dagger_iterations=a.dagger_iterations,
    )
    print(json.dumps({"label": r["label"], **{pl: r[pl]["vs_baseline"] for pl in PLANTS if pl in r}}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
