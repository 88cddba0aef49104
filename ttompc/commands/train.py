"""``ttompc train [RECIPE.yaml] key=value ...``: pre-train a trajectory transformer (settings: ``TrainConfig``).

Example: ``ttompc train recipes/freeflyer/tiny.yaml data.paths=[data/freeflyer-v1] trainer.max_steps=500``.
Re-running the same command with the same ``trainer.out_dir`` resumes from the newest checkpoint that loads."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ttompc.config import add_config_arguments, split_recipe, to_container
from ttompc.data.config import DataConfig
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


def check_datasets(data: DataConfig) -> None:
    """Every dataset folder must exist and fit the recipe (``open_loop_manifests``) before anything is created or
    imported (Lightning is slow to import; docs/design.md)."""
    paths, dagger_dirs = data.paths, data.dagger_dirs
    if not paths and not dagger_dirs:
        raise UserError(
            "no training data: data.paths is empty (the recipe leaves it to the command line)",
            "pass data.paths=[FOLDER], a dataset written by `ttompc generate`",
        )
    for key, folders in (("data.paths", paths), ("data.dagger_dirs", dagger_dirs)):
        missing = [p for p in folders if not Path(p).is_dir()]
        if missing:
            raise UserError(
                f"{key}: dataset folder {missing[0]} does not exist",
                f"make it with `ttompc generate out={missing[0]} ...` or point {key}=[...] at existing folders",
            )
    from ttompc.data.generate import MANIFEST, open_loop_manifests
    from ttompc.data.resumable import META_DIR

    for folder in map(Path, paths):
        if (folder / MANIFEST).is_file():
            continue
        if (folder / META_DIR).is_dir():
            raise UserError(
                f"data.paths: the generation of {folder} is not finished (no {MANIFEST})",
                "re-run the same `ttompc generate` command (add --finalize once every rank's shards exist)",
            )
        raise UserError(
            f"data.paths: {folder} is not a dataset made by `ttompc generate` (no {MANIFEST})",
            "point data.paths=[...] at a folder written by `ttompc generate`",
        )
    if paths:
        open_loop_manifests(data)


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
        print(json.dumps(to_container(cfg), indent=2))
        print(f"# {MAX_STEPS_HELP}", file=sys.stderr)  # JSON has no comments; stdout stays the config alone
        return 0
    check_datasets(cfg.data)
    # an out_dir the user may not write fails here, in one line, not after Lightning and the shard checksums
    Path(cfg.trainer.out_dir).mkdir(parents=True, exist_ok=True)
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
