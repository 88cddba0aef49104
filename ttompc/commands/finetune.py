"""``ttompc finetune [RECIPE.yaml] --model MODEL key=value ...``: DAgger fine-tuning for MPC (paper Alg. 1).

Settings are ``FinetuneConfig`` keys. MODEL is a zoo model name, hf://ORG/NAME[@REV], a planner bundle directory or
a Lightning checkpoint. The model, the recipe and the open-loop data are checked against each other (scenario,
normalisation statistics, labels: ``ttompc.finetune.loop.check_inputs``) before anything is written, measured or
collected. Re-running the same command with the same ``trainer.out_dir`` resumes after the last finished
iteration (collected shards are not recollected).
Under torchrun/SLURM every rank collects its own slice of the rollouts."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ttompc.config import add_config_arguments, split_recipe
from ttompc.errors import ConfigError, UserError
from ttompc.finetune.config import FinetuneConfig, load_finetune_config
from ttompc.progress import status


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_config_arguments(parser, "recipes/freeflyer/finetune.yaml dagger.iterations=3")
    parser.add_argument(
        "--model", help="pretrained model: zoo name, hf://ORG/NAME[@REV], bundle directory or Lightning .ckpt"
    )


def _config(args: argparse.Namespace) -> FinetuneConfig:
    recipe, overrides = split_recipe(args.settings)
    return load_finetune_config(recipe, overrides)


def output_dir(args: argparse.Namespace) -> str:
    return _config(args).trainer.out_dir


def resume_hint(args: argparse.Namespace) -> str:
    try:
        out_dir = output_dir(args)
    except UserError:
        out_dir = "trainer.out_dir"
    return f"re-run the same command to continue after the last finished iteration (kept in {out_dir})"


def _check_against_data(cfg: FinetuneConfig) -> None:
    """The devices the recipe names exist here, ``trainer.out_dir`` is new, empty or a DAgger run's (its state file
    or source planner: the run checks its source and seed itself), and the learners' horizons fit the data's N (a
    longer one would be cut to N under its own name) where its manifest is there (``finetune`` checks the data
    against the model, ``ttompc.finetune.loop.check_inputs``)."""
    from ttompc.data.manifests import MANIFEST, load_manifest
    from ttompc.finetune.loop import claim_run

    claim_run(cfg)
    if not (Path(cfg.data.paths[0]) / MANIFEST).is_file():
        return
    n_steps = int(load_manifest(cfg.data.paths[0])["scenario"]["n_steps"])
    horizons = cfg.dagger.exploration.horizons
    if max(horizons) > n_steps:
        raise ConfigError(
            f"invalid dagger.exploration.horizons={horizons}: the data's trajectories have {n_steps} steps",
            f"use horizons within [1, {n_steps}]",
        )


def run(args: argparse.Namespace) -> int:
    cfg = _config(args)
    if args.print_config:
        from ttompc.evaluation.measurement import with_settings

        print(json.dumps(with_settings(cfg), indent=2))
        return 0
    if args.model is None:
        raise UserError("no model to fine-tune", "pass --model NAME (e.g. --model freeflyer-tto-v3)")
    if not cfg.data.paths:
        raise UserError(
            "no open-loop data: data.paths is empty (the recipe leaves it to the command line)",
            "pass data.paths=[FOLDER], the dataset written by `ttompc generate` that the model was trained on",
        )
    _check_against_data(cfg)
    status(f"ttompc finetune: loading {args.model} and Lightning")
    from ttompc.finetune import finetune

    result = finetune(cfg, args.model)
    print(
        json.dumps(
            {
                "run_dir": str(result.run_dir),
                "planner": str(result.planner_dir),
                "best_iteration": result.best_iteration,
                "baseline_metrics": result.baseline_metrics,
                "iterations": result.iterations,
            }
        )
    )
    return 0
