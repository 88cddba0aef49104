"""The ``ttompc`` console entry point. A thin dispatcher: each subcommand lives in ``ttompc.commands.<name>`` with
``add_arguments(parser)`` and ``run(args) -> int``, imported only when used so ``ttompc solve`` stays fast."""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

COMMANDS: dict[str, tuple[str, str]] = {
    "solve": ("ttompc.commands.solve", "sample a problem, solve REL then SCP, print a table (and plot)"),
    "generate": ("ttompc.commands.generate", "generate a trajectory dataset into parquet shards"),
    "train": ("ttompc.commands.train", "pre-train a trajectory transformer from a recipe"),
    "finetune": ("ttompc.commands.finetune", "DAgger fine-tuning of a trained transformer"),
    "evaluate": ("ttompc.commands.evaluate", "warm-start and MPC evaluations"),
    "zoo": ("ttompc.commands.zoo", "list, inspect, download and publish pretrained models"),
    "demo": ("ttompc.commands.demo", "the quickstart: plan seeded problems with a shipped zoo model"),
}


def build_parser(argv: Sequence[str]) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ttompc", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    wanted = next((a for a in argv if not a.startswith("-")), None)
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text)
        if name == wanted:  # only import the module of the command being run
            importlib.import_module(module).add_arguments(p)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser(argv).parse_args(argv)
    module = importlib.import_module(COMMANDS[args.command][0])
    return int(module.run(args) or 0)


if __name__ == "__main__":
    raise SystemExit(main())
