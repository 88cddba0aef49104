"""``ttompc train RECIPE [key=value ...]``: pre-train a trajectory transformer from a YAML recipe.

Re-running the same command with the same ``trainer.out_dir`` resumes from its ``last.ckpt``."""

from __future__ import annotations

import argparse
import json


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recipe", help="YAML recipe, e.g. recipes/freeflyer/pretrain.yaml")
    parser.add_argument("overrides", nargs="*", metavar="key=value", help="dot-list overrides, e.g. optim.lr=1e-4")
    parser.add_argument("--print-config", action="store_true", help="print the resolved config and exit")


def run(args: argparse.Namespace) -> int:
    import sys

    from ttompc.config import ConfigError, to_container
    from ttompc.training.config import load_train_config

    try:
        cfg = load_train_config(args.recipe, args.overrides)
    except ConfigError as err:
        print(f"ttompc train: {err}", file=sys.stderr)
        return 2
    if args.print_config:
        print(json.dumps(to_container(cfg), indent=2))
        return 0
    from ttompc.training.run import train

    result = train(cfg)
    print(
        json.dumps(
            {
                "out_dir": str(result.out_dir),
                "start_step": result.start_step,
                "global_step": result.global_step,
                "last_checkpoint": str(result.last_checkpoint),
                "planner": str(result.planner_dir) if result.planner_dir else None,
                "metrics": result.metrics,
            }
        )
    )
    return 0
