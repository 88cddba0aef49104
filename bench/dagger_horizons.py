"""DAgger collection with mixed horizons: the paper recipes' rollouts in lockstep batches.

The paper's exploration draws H per rollout from U{10..100}, so the learners of one lockstep batch ask windows of
different lengths at every step. Variants, on the same rollouts (problems, H, expert windows, labels):

* ``before``: the group as before item 5: a batched rollout (and every member's conditioning) whenever a request's
  length differs from the previous one's (emulated on the current group).
* ``lazy``: a rollout only for a request longer than the step's rollout so far; shorter ones are its prefix.
* ``batched`` (what ships): the step's longest window is announced (``RolloutGroup.expect``): one rollout per step.

The three give the same rows bitwise (checked: a window is the prefix of a longer rollout). Per variant: CPU-s per
rollout (all of it, and inside ``RolloutContext.rollout``), batched rollouts and generated steps per lockstep step.
The label schedule is the recipe's unless ``--labels`` (labels add expert solves, not transformer work). CPU-seconds
are this process's (one torch thread).

    python bench/dagger_horizons.py --scenario freeflyer --model freeflyer-ft-tto-v5 --rollouts 20 --labels 5

Ends with one JSON line, also written to bench/results/dagger_horizons_<scenario>.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import torch
from record import Machine, result_path, write_result

from ttompc.finetune.collect import collect_rollouts
from ttompc.finetune.config import load_finetune_config
from ttompc.mpc.tto import RolloutGroup
from ttompc.policy import Planner
from ttompc.policy.rollout import RolloutContext
from ttompc.scenarios import get_scenario
from ttompc.scenarios.base import Window

VARIANTS = ("before", "lazy", "batched")


@contextmanager
def patched(obj: Any, name: str, value: Any) -> Iterator[None]:
    old = getattr(obj, name)
    setattr(obj, name, value)
    try:
        yield
    finally:
        setattr(obj, name, old)


@contextmanager
def variant(name: str, rollouts: list[tuple[int, float]]) -> Iterator[None]:
    """The group of ``name``; every rollout run appends (horizon, CPU-s) to ``rollouts``."""
    run, request = RolloutContext.rollout, RolloutGroup.rollout

    def timed(ctx: RolloutContext, horizon: int) -> Any:
        t0 = time.process_time()
        res = run(ctx, horizon)
        rollouts.append((horizon, time.process_time() - t0))
        return res

    def before(group: RolloutGroup, slot: int, window: Window) -> Any:
        if group._plan is not None and group._plan[1].shape[1] != window.length:  # the old cache key: the length
            group._own, group._plan = [], None
        return request(group, slot, window)

    no_hint: Callable[..., None] = lambda group, start, length: None  # noqa: E731
    with patched(RolloutContext, "rollout", timed):
        if name == "batched":
            yield
            return
        with patched(RolloutGroup, "expect", no_hint):
            if name == "lazy":
                yield
                return
            with patched(RolloutGroup, "rollout", before):
                yield


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="freeflyer")
    ap.add_argument("--model", default="freeflyer-ft-tto-v5", help="zoo name, bundle folder or checkpoint")
    ap.add_argument("--recipe", default=None, help="default: recipes/<scenario>/paper-finetune.yaml")
    ap.add_argument("--rollouts", type=int, default=10)
    ap.add_argument("--batch", type=int, default=None, help="rollouts in lockstep (default: the recipe's)")
    ap.add_argument("--labels", type=int, default=None, help="labelled steps per rollout (default: the recipe's)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    root = Path(__file__).resolve().parents[1]
    recipe = args.recipe or root / "recipes" / args.scenario / "paper-finetune.yaml"
    dagger = load_finetune_config(recipe).dagger
    labels = dagger.labels if args.labels is None else dataclasses.replace(dagger.labels, per_rollout=args.labels)
    batch = args.batch or dagger.collect.batch
    scenario = get_scenario(args.scenario)
    planner = Planner.from_pretrained(args.model, scenario)
    machine = Machine()
    cpu: dict[str, float] = dict.fromkeys(VARIANTS, 0.0)
    runs: dict[str, list[tuple[int, float]]] = {name: [] for name in VARIANTS}
    steps = 0
    for start in range(0, args.rollouts, batch):
        chunk = list(range(start, min(start + batch, args.rollouts)))
        rows = {}
        for name in VARIANTS:  # alternating, so that machine drift hits all alike
            with variant(name, runs[name]):
                t0 = time.process_time()
                rows[name] = collect_rollouts(
                    scenario, planner, 0, chunk, dagger.seed, dagger.exploration, labels, settings=dagger.eval.settings
                )
                cpu[name] += time.process_time() - t0
        for name in VARIANTS[:-1]:
            for a, b in zip(rows[name], rows["batched"], strict=True):
                assert all(np.array_equal(x["states"], y["states"]) for x, y in zip(a, b, strict=True)), name
        steps += scenario.n_steps
    results = {
        name: {
            "cpu_s_per_rollout": cpu[name] / args.rollouts,
            "rollout_cpu_s_per_rollout": sum(s for _, s in runs[name]) / args.rollouts,
            "rollouts_per_step": len(runs[name]) / steps,
            "generated_steps_per_step": sum(h for h, _ in runs[name]) / steps,
        }
        for name in VARIANTS
    }
    summary = {
        "bench": "dagger_horizons",
        "scenario": args.scenario,
        "model": args.model,
        "recipe": str(recipe),
        "rollouts": args.rollouts,
        "batch": batch,
        "labels_per_rollout": labels.per_rollout,
        "results": results,
        "speedup_vs_before": results["before"]["cpu_s_per_rollout"] / results["batched"]["cpu_s_per_rollout"],
        "rollout_speedup_vs_before": results["before"]["rollout_cpu_s_per_rollout"]
        / results["batched"]["rollout_cpu_s_per_rollout"],
        **machine.record(),
    }
    write_result(summary, args.out or result_path(f"dagger_horizons_{args.scenario}"))


if __name__ == "__main__":
    main()
