"""Step latency of ``ttompc.Controller`` at batch 1: one robot, one core (issue 54).

For each scenario and its shipped fine-tuned model, on the first ``--problems`` held-out non-convex problems of the
evaluation stream of ``--seed`` (``eval_problem``), every row drives the nominal plant through whole episodes with a
Controller, one ``step(x)`` per control, and records each step's wall time (``StepRecord.seconds``: from the measured
state to the control; perf_counter): the mean and the 99th percentile over all steps of all its episodes, the
largest step, and the goals reached. Rows:

* the model's learned MPC at H = 10 under ``protocol=recommended`` (``Controller.from_pretrained``: its robust
  TTO-MPC, fused decoder, RTI where the scenario declares it);
* REL-MPC at H = 10 under the same protocol (the same loop without a model);
* REL-MPC at H = 30 under ``protocol=paper``, the baseline (the paper's REL-MPC at the horizon it needs for the
  cost the learned MPC reaches at H = 10): each row's ``ratio_mean`` and ``ratio_p99`` are the baseline's over the
  row's, in the same run.

The rows' episodes of one problem run in lockstep, one step of each row in turn, so a changing machine load lands
on every row alike. torch runs one
thread. The Controllers are built (and their kernels compiled or loaded, ``ttompc.mpc.warmup``) before any timed
step. Ends with one JSON line, also written to bench/results/controller_latency.json (``--out``).
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np
import torch
from record import Machine, result_path, write_result

from ttompc.evaluation.problems import eval_problem
from ttompc.mpc.controller import Controller
from ttompc.mpc.plant import Plant

MODELS = {"freeflyer": "freeflyer-ft-tto-v5", "quadrotor": "quadrotor-ft-tto-v6", "rpod": "rpod-ft-tto-v4"}
BASELINE = "REL-MPC@30"


def controllers(scenario: str) -> dict[str, Controller]:
    """The rows of one scenario (module doc), keyed "METHOD@H"."""
    learned = Controller.from_pretrained(MODELS[scenario], horizon=10, protocol="recommended")
    return {
        f"{learned.name}@10": learned,
        "REL-MPC@10": Controller(scenario, "REL-MPC", horizon=10, protocol="recommended"),
        BASELINE: Controller(scenario, "REL-MPC", horizon=30, protocol="paper"),
    }


def episodes(rows: dict[str, Controller], problem: Any, rel_cost: float) -> dict[str, tuple[list[float], bool]]:
    """One episode per row on the nominal plant, stepped in turn (row 1's step t, row 2's, ..., then step t + 1):
    each row's step wall times (s) and whether it reached the goal."""
    sc = next(iter(rows.values())).scenario
    xs, times = {}, {key: [] for key in rows}
    for key, ctrl in rows.items():
        ctrl.reset(problem, rel_cost)
        xs[key] = problem.x0.copy()
    plant = Plant(sc)  # the nominal plant: the exact dynamics, no draws
    for t in range(problem.n_steps):
        for key, ctrl in rows.items():
            u = ctrl.step(xs[key])
            assert ctrl.last is not None
            times[key].append(ctrl.last.seconds)
            xs[key] = plant.step(problem, t, xs[key], u)
    return {key: (times[key], bool(np.linalg.norm(xs[key] - problem.goal) <= sc.terminal_tol)) for key in rows}


def measure(scenario: str, problems: int, seed: int) -> dict[str, dict[str, float]]:
    rows = controllers(scenario)
    times: dict[str, list[float]] = {key: [] for key in rows}
    goals = dict.fromkeys(rows, 0)
    for i in range(problems):
        ep = eval_problem(rows[BASELINE].scenario, seed, i)
        for key, (t, goal) in episodes(rows, ep.problem, ep.rel_cost).items():
            times[key] += t
            goals[key] += goal
    out = {}
    for key, t in times.items():
        a = 1e3 * np.asarray(t)
        out[key] = {
            "mean_ms": float(a.mean()),
            "p99_ms": float(np.percentile(a, 99)),
            "max_ms": float(a.max()),
            "steps": len(a),
            "goals": goals[key],
            "episodes": problems,
        }
    base = out[BASELINE]
    for row in out.values():
        row["ratio_mean"] = base["mean_ms"] / row["mean_ms"]
        row["ratio_p99"] = base["p99_ms"] / row["p99_ms"]
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--problems", type=int, default=2, help="held-out problems per scenario (default 2)")
    p.add_argument("--scenarios", nargs="+", default=list(MODELS), choices=list(MODELS))
    p.add_argument("--seed", type=int, default=4242, help="root seed of the evaluation problems (the zoo cards')")
    p.add_argument("--out", default=str(result_path("controller_latency")))
    args = p.parse_args()
    torch.set_num_threads(1)
    machine = Machine()
    result: dict[str, Any] = {"bench": "controller_latency", "problems": args.problems, "seed": args.seed}
    result["scenarios"] = {sc: measure(sc, args.problems, args.seed) for sc in args.scenarios}
    result["machine"] = machine.record()
    line = {
        sc: {k: [round(r["mean_ms"], 2), round(r["p99_ms"], 2), round(r["ratio_mean"], 2)] for k, r in rows.items()}
        for sc, rows in result["scenarios"].items()
    }
    write_result(result, args.out, {"bench": "controller_latency", "mean_p99_ms_ratio": line})


if __name__ == "__main__":
    main()
