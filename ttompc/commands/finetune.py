"""``ttompc finetune RECIPE --from MODEL [key=value ...]``: DAgger fine-tuning for MPC (paper Alg. 1).

MODEL is a Lightning checkpoint, a planner bundle directory or a zoo model name. Re-running the same command with
the same ``trainer.out_dir`` resumes after the last finished iteration (collected shards are not recollected).
Under torchrun/SLURM every rank collects its own slice of the rollouts."""

from __future__ import annotations

import argparse
import json
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recipe", help="YAML recipe, e.g. recipes/freeflyer/finetune.yaml")
    parser.add_argument(
        "overrides", nargs="*", metavar="key=value", help="dot-list overrides, e.g. dagger.iterations=3"
    )
    # nargs="+": overrides may also follow the model (`--from MODEL key=value ...`), which a plain positional list
    # cannot take after an option
    parser.add_argument(
        "--from",
        dest="source",
        nargs="+",
        metavar="MODEL",
        help="pretrained model (.ckpt, bundle directory or zoo name), optionally followed by key=value overrides",
    )
    parser.add_argument("--print-config", action="store_true", help="print the resolved config and exit")


def run(args: argparse.Namespace) -> int:
    from ttompc.config import ConfigError, to_container
    from ttompc.finetune.config import load_finetune_config

    source, *more = args.source or [None]
    try:
        cfg = load_finetune_config(args.recipe, [*args.overrides, *more])
    except ConfigError as err:
        print(f"ttompc finetune: {err}", file=sys.stderr)
        return 2
    if args.print_config:
        print(json.dumps(to_container(cfg), indent=2))
        return 0
    if source is None:
        print("ttompc finetune: --from MODEL is required", file=sys.stderr)
        return 2
    from ttompc.finetune.dagger import finetune

    result = finetune(cfg, source)
    print(
        json.dumps(
            {
                "run_dir": str(result.run_dir),
                "baseline_metrics": result.baseline_metrics,
                "iterations": result.iterations,
            }
        )
    )
    return 0
