"""``ttompc generate [RECIPE.yaml] key=value ...``: sample and solve problems into parquet shards (resumable,
multi-process, multi-rank). Settings are ``GenerateConfig`` keys; the flags are shortcuts for them.

Examples:
    ttompc generate scenario=freeflyer problems=20000 out=data/freeflyer-v1 workers=8
    ttompc generate --scenario freeflyer --problems 20000 --out data/freeflyer-v1 --workers 8   # the same
    torchrun --nproc-per-node 4 -m ttompc.cli generate ... finalize_wait_s=3600   # ranks split the shards
    ttompc generate ... --finalize      # write manifest + card once all ranks' shards exist
"""

from __future__ import annotations

import argparse
import json

from ttompc.commands import checks
from ttompc.config import add_config_arguments, load_command_config, shortcut_overrides, split_recipe, to_container
from ttompc.data.config import GenerateConfig
from ttompc.errors import UserError

# shortcut flags: argparse dest -> GenerateConfig key, the same name but for --finalize-wait and --split-salt
_SAME = ("scenario", "problems", "out", "seed", "shard_size", "workers", "backend", "solver", "max_shards", "name")
_FLAGS = {**{name: name for name in _SAME}, "finalize_wait": "finalize_wait_s", "split_salt": "splits.salt"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_config_arguments(parser, "scenario=quadrotor problems=2000 out=data/quadrotor-v1")
    parser.add_argument("--scenario", help="a name, module:Class or path/to/file.py:Class (default freeflyer)")
    parser.add_argument("--problems", type=int, help="number of problems (default 20000)")
    parser.add_argument("--out", help="output folder (default data/freeflyer-v1)")
    parser.add_argument("--seed", type=int, help="root seed (default 0)")
    parser.add_argument("--shard-size", type=int, help="problems per shard (default 500)")
    parser.add_argument("--workers", type=int, help="worker processes (default: all cores)")
    parser.add_argument("--backend", help="convex solver backend passed to the SCP engine")
    parser.add_argument("--solver", help="'module:function' with solve_problem's signature")
    parser.add_argument("--max-shards", type=int, help="stop after this many new shards (resume later)")
    parser.add_argument("--splits", help="train,val,test problem fractions (default 0.9,0.05,0.05)")
    parser.add_argument("--split-salt", type=int, help="salt of the split hash (default 0)")
    parser.add_argument("--name", help="dataset name for the card (default: folder name)")
    parser.add_argument("--finalize-wait", type=float, help="rank 0 waits this many s for other ranks' shards")
    parser.add_argument("--finalize", action="store_true", help="only write manifest.json and README.md")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def config_from_args(args: argparse.Namespace) -> GenerateConfig:
    """Recipe <- shortcut flags <- ``key=value`` settings, checked before any folder is created."""
    recipe, overrides = split_recipe(args.settings)
    flags = [*shortcut_overrides(args, _FLAGS), *_split_fractions(args.splits)]
    cfg = load_command_config(GenerateConfig, recipe, [*flags, *overrides])
    checks.scenario(cfg.scenario)
    checks.backend(cfg.backend)
    checks.solver(cfg.solver)
    return cfg


def _split_fractions(text: str | None) -> list[str]:
    if not text:
        return []
    parts = text.split(",")
    if len(parts) != 3:
        raise UserError(f"--splits needs three comma-separated fractions, got {text!r}", "e.g. --splits 0.8,0.1,0.1")
    return [f"splits.{s}={p}" for s, p in zip(("train", "val", "test"), parts, strict=True)]


def resume_hint(args: argparse.Namespace) -> str:
    kept = f"finished shards in {output_dir(args)} are kept"
    return f"re-run the same command to generate only the missing shards ({kept})"


def output_dir(args: argparse.Namespace) -> str:
    return config_from_args(args).out


def run(args: argparse.Namespace) -> int:
    from ttompc.data.generate import GenerationError, finalize, generate
    from ttompc.data.shards import ShardError

    cfg = config_from_args(args)
    if args.print_config:
        print(json.dumps(to_container(cfg), indent=2))
        return 0
    checks.writable(cfg.out)
    try:
        manifest = finalize(cfg) if args.finalize else generate(cfg, progress=not args.no_progress)
    except (GenerationError, ShardError) as err:
        raise UserError(str(err)) from err
    if manifest is None:
        print(
            f"shards written to {cfg.out}; manifest not written yet (other ranks' shards missing or max_shards "
            "reached): re-run with the same arguments, or add --finalize once all shards exist"
        )
        return 0
    summary = {
        "out": cfg.out,
        "rows": manifest["counts"]["rows"],
        "failures": manifest["counts"]["failures"],
        "splits": manifest["splits"]["problems"],
    }
    print(json.dumps(summary))
    return 0
