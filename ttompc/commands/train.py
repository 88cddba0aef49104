"""``ttompc train [RECIPE.yaml] key=value ...``: pre-train a trajectory transformer (settings: ``TrainConfig``).

Example: ``ttompc train recipes/freeflyer/tiny.yaml data.paths=[data/freeflyer-v1] trainer.max_steps=500``.
Re-running the same command with the same ``trainer.out_dir`` resumes from the newest checkpoint that loads."""

from __future__ import annotations

import argparse
import json
import sys

from ttompc.config import add_config_arguments, split_recipe
from ttompc.errors import UserError
from ttompc.progress import status
from ttompc.training.config import TrainConfig, load_train_config

# Three keys of a recipe share the name max_steps (the bundles' config.json holds model.max_steps, so it stays):
# --help and --print-config say which is which.
MAX_STEPS_HELP = (
    "Three settings are called max_steps and mean different things: model.max_steps is the longest trajectory the "
    "model takes, in control steps (the size of its timestep embedding, fixed by the weights: at least the "
    "scenario's horizon N); trainer.max_steps is how long to train, in optimiser steps; "
    "callbacks.eval_mpc.max_steps cuts the closed-loop evaluation episodes to that many MPC steps (null: whole "
    "episodes)."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_config_arguments(parser, "recipes/freeflyer/tiny.yaml data.paths=[data/freeflyer-v1] optim.lr=1e-4")
    parser.epilog = MAX_STEPS_HELP


def _config(args: argparse.Namespace) -> TrainConfig:
    recipe, overrides = split_recipe(args.settings)
    return load_train_config(recipe, overrides)


def output_dir(args: argparse.Namespace) -> str:
    return _config(args).trainer.out_dir


def resume_hint(args: argparse.Namespace) -> str:
    try:
        out_dir = output_dir(args)
    except UserError:
        out_dir = "trainer.out_dir"
    return f"re-run the same command to resume from the newest checkpoint (checkpoints in {out_dir} are kept)"


def run(args: argparse.Namespace) -> int:
    cfg = _config(args)
    if args.print_config:
        from ttompc.evaluation.measurement import with_settings

        print(json.dumps(with_settings(cfg), indent=2))
        print(f"# {MAX_STEPS_HELP}", file=sys.stderr)  # JSON has no comments; stdout stays the config alone
        return 0
    from ttompc.training.preflight import prepare_run

    # devices, every dataset folder, and the out_dir as this run's (new, empty or its own checkpoints), checked
    # before the status line, Lightning and the shard checksums (train() checks them again: a no-op by then)
    prepare_run(cfg)
    status("ttompc train: loading Lightning and the data")
    from ttompc.data.shards import ShardError
    from ttompc.training.run import train

    try:
        result = train(cfg)
    except ShardError as err:
        raise UserError(str(err), "check the dataset folder (re-run `ttompc generate` with the same settings)") from err
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
