"""``ttompc generate``: sample and solve problems into parquet shards (resumable, multi-process, multi-rank).

Examples:
    ttompc generate --scenario freeflyer --problems 20000 --out data/freeflyer-v1 --workers 8
    torchrun --nproc-per-node 4 -m ttompc.cli generate ... --finalize-wait 3600   # ranks split the shards
    ttompc generate ... --finalize      # write manifest + card once all ranks' shards exist
"""

from __future__ import annotations

import argparse
import json

from ttompc.config import load_config
from ttompc.data.config import GenerateConfig

# flag -> GenerateConfig key
_FLAGS = {
    "scenario": "scenario",
    "problems": "problems",
    "out": "out",
    "seed": "seed",
    "shard_size": "shard_size",
    "workers": "workers",
    "backend": "backend",
    "solver": "solver",
    "max_shards": "max_shards",
    "finalize_wait": "finalize_wait_s",
    "name": "name",
    "split_salt": "splits.salt",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="YAML file with GenerateConfig fields (flags override it)")
    parser.add_argument("--scenario", help="registered scenario name (default freeflyer)")
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
    parser.add_argument("overrides", nargs="*", help="extra key=value GenerateConfig overrides")


def config_from_args(args: argparse.Namespace) -> GenerateConfig:
    overrides = [f"{key}={getattr(args, flag)}" for flag, key in _FLAGS.items() if getattr(args, flag) is not None]
    if args.splits:
        parts = args.splits.split(",")
        if len(parts) != 3:
            raise SystemExit(f"--splits needs three comma-separated fractions, got {args.splits!r}")
        overrides += [f"splits.{s}={p}" for s, p in zip(("train", "val", "test"), parts, strict=True)]
    return load_config(GenerateConfig, args.config, [*overrides, *args.overrides])


def run(args: argparse.Namespace) -> int:
    from ttompc.data.generate import finalize, generate

    cfg = config_from_args(args)
    manifest = finalize(cfg) if args.finalize else generate(cfg, progress=not args.no_progress)
    if manifest is None:
        print(
            f"shards written to {cfg.out}; manifest not written yet (other ranks' shards missing or --max-shards "
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
