"""DAgger collection speed: labelled rollouts per CPU-second, the paper's collection and the recipes', one run.

Rows (each rollout index collected once per variant, variants alternating so that machine drift hits all alike):
* ``paper``: the paper's exploration (H ~ U{10..100}, 1–3 expert windows, one at the end) and an expert label at every
  visited step (``labels.kind=step``, ``per_rollout=0``): how the paper's DAgger iterations collect.
* ``subsampled``: the same exploration, labels on ``--labels`` random steps per rollout (a departure; the loss skips
  the others): the labelling lever alone.
* ``v4``: the FT-v4 recipes' collection: the deployed policy (TTO-MPC at H = 10, no expert windows) with ``plan``
  labels on ``--labels`` steps per rollout, one rollout at a time.
* ``v4-batched``: the same rollouts run ``--batch`` at a time in lockstep (``collect_rollouts``, ``collect.batch``):
  one batched transformer rollout per step for all of them.
CPU-seconds are this process's (``time.process_time``, one torch thread), so a loaded machine changes them less than
the wall time. Per variant: CPU-s per rollout, labels and training rows per rollout, and the projected CPU-minutes for
1,000 rollouts on one core; the ratios are paper / v4 and paper / v4-batched CPU-s per rollout. Collection runs on
one core per process and scales over processes and ranks (``dagger.collect.workers``, torchrun), so rollouts per
CPU-second is the unit.

    python bench/dagger_speed.py --scenario freeflyer --model freeflyer-tto-v3 --rollouts 10 --batch 10

Ends with one JSON line, also written to bench/results/dagger_speed_<scenario>.json.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from record import Machine, result_path, write_result

from ttompc.finetune.collect import collect_rollout, collect_rollouts
from ttompc.finetune.config import ExplorationConfig, LabelConfig
from ttompc.policy import Planner
from ttompc.scenarios import get_scenario


def variants(labels: int) -> dict[str, tuple[ExplorationConfig, LabelConfig]]:
    v4 = ExplorationConfig(horizons=[10], windows=[0, 0], end_window=False)
    return {
        "paper": (ExplorationConfig(), LabelConfig()),
        "subsampled": (ExplorationConfig(), LabelConfig(kind="step", per_rollout=labels)),
        "v4": (v4, LabelConfig(kind="plan", per_rollout=labels, rtg="expert")),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="freeflyer")
    ap.add_argument("--model", default="freeflyer-tto-v3", help="zoo name, bundle folder or checkpoint")
    ap.add_argument("--rollouts", type=int, default=10, help="rollouts per variant")
    ap.add_argument("--batch", type=int, default=10, help="rollouts in lockstep in the v4-batched variant")
    ap.add_argument("--labels", type=int, default=10, help="labelled steps per rollout of the subsampled variants")
    ap.add_argument("--seed", type=int, default=27)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    scenario = get_scenario(args.scenario)
    planner = Planner.from_pretrained(args.model, scenario)
    machine = Machine()
    cpu: dict[str, list[float]] = {}
    labels: dict[str, list[int]] = {}
    rows: dict[str, list[int]] = {}
    for r in range(args.rollouts):
        for name, (explore, label) in variants(args.labels).items():
            t0 = time.process_time()
            out = collect_rollout(scenario, planner, 0, r, args.seed, explore, label)
            cpu.setdefault(name, []).append(time.process_time() - t0)
            labels.setdefault(name, []).append(int(out[0]["status"].split("labels=")[1].split(";")[0]))
            rows.setdefault(name, []).append(len(out))
    explore, label = variants(args.labels)["v4"]
    for start in range(0, args.rollouts, args.batch):
        chunk = list(range(start, min(start + args.batch, args.rollouts)))
        t0 = time.process_time()
        outs = collect_rollouts(scenario, planner, 0, chunk, args.seed, explore, label)
        cpu.setdefault("v4-batched", []).extend([(time.process_time() - t0) / len(chunk)] * len(chunk))
        labels.setdefault("v4-batched", []).extend(
            int(out[0]["status"].split("labels=")[1].split(";")[0]) for out in outs
        )
        rows.setdefault("v4-batched", []).extend(len(out) for out in outs)
    results = {
        name: {
            "cpu_s_per_rollout": float(np.mean(c)),
            "rollouts_per_cpu_s": 1.0 / float(np.mean(c)),
            "labels_per_rollout": float(np.mean(labels[name])),
            "rows_per_rollout": float(np.mean(rows[name])),
            "cpu_min_per_1000_rollouts": 1000 * float(np.mean(c)) / 60,
        }
        for name, c in cpu.items()
    }
    summary = {
        "bench": "dagger_speed",
        "scenario": args.scenario,
        "model": args.model,
        "rollouts_per_variant": args.rollouts,
        "labels": args.labels,
        "results": results,
        "speedup_v4_vs_paper": results["paper"]["cpu_s_per_rollout"] / results["v4"]["cpu_s_per_rollout"],
        "speedup_subsampled_vs_paper": results["paper"]["cpu_s_per_rollout"]
        / results["subsampled"]["cpu_s_per_rollout"],
        "speedup_batched_vs_paper": results["paper"]["cpu_s_per_rollout"] / results["v4-batched"]["cpu_s_per_rollout"],
        "speedup_batched_vs_v4": results["v4"]["cpu_s_per_rollout"] / results["v4-batched"]["cpu_s_per_rollout"],
        "batch": args.batch,
        **machine.record(),
    }
    write_result(summary, args.out or result_path(f"dagger_speed_{args.scenario}"))


if __name__ == "__main__":
    main()
