"""ttompc: plan spacecraft and robot trajectories with a transformer that warm-starts SCP and MPC.

The ``ttompc`` console entry point is a thin dispatcher: each subcommand lives in ``ttompc.commands.<name>`` with
``add_arguments(parser)``, ``run(args) -> int`` and optionally ``resume_hint(args) -> str`` (what to do after
Ctrl-C or a full disk) and ``output_dir(args) -> str`` (where it writes), imported only when used so
``ttompc solve`` stays fast (no Lightning).

One error path for every command: a ``UserError`` (bad settings, unknown names, missing or damaged files) prints
one line naming the problem and what to do and exits with 2, and so does a path the command may not use (no
permission, a read-only file system, a file where a folder should be); Ctrl-C says how to resume and exits with 130;
a full disk says which path is full and that completed work is kept. ``--debug`` (anywhere on the command line) or
``TTOMPC_DEBUG=1`` re-raises instead, with the traceback.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import os
import signal
import sys
from collections.abc import Sequence
from types import ModuleType

from ttompc.errors import UserError
from ttompc.parallel import starting_worker

COMMANDS: dict[str, tuple[str, str]] = {
    "solve": ("ttompc.commands.solve", "sample a problem, solve REL then SCP, print a table (and plot)"),
    "generate": ("ttompc.commands.generate", "generate a trajectory dataset into parquet shards"),
    "train": ("ttompc.commands.train", "pre-train a trajectory transformer from a recipe"),
    "finetune": ("ttompc.commands.finetune", "DAgger fine-tuning of a trained transformer"),
    "evaluate": ("ttompc.commands.evaluate", "warm-start and MPC evaluations"),
    "zoo": ("ttompc.commands.zoo", "list, inspect, download and publish pretrained models"),
    "demo": ("ttompc.commands.demo", "the quickstart: zoo models' warm starts and MPC against REL's, one table"),
    "check-scenario": (
        "ttompc.commands.check_scenario",
        "check your scenario against the interface (docs/scenarios.md)",
    ),
}
EXIT_USER_ERROR = 2
EXIT_INTERRUPTED = 130
# OSErrors about a path the user chose (permissions, read-only file system, a file where a folder should be)
_UNUSABLE_PATH = (errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOTDIR, errno.EISDIR, errno.EEXIST)

_EPILOG = (
    "Every command takes `ttompc COMMAND [RECIPE.yaml] key=value ...`; flags are shortcuts for keys. "
    "`ttompc COMMAND --help` lists them. --debug (or TTOMPC_DEBUG=1) shows tracebacks."
)


def build_parser(argv: Sequence[str]) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ttompc", description=__doc__.splitlines()[0], epilog=_EPILOG)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    wanted = next((a for a in argv if not a.startswith("-")), None)
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == wanted:  # only import the module of the command being run
            importlib.import_module(module).add_arguments(p)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    if starting_worker():  # a pool worker importing an unguarded script that calls main(): the parent reports it
        raise SystemExit(EXIT_USER_ERROR)
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv or os.environ.get("TTOMPC_DEBUG", "") not in ("", "0")
    argv = [a for a in argv if a != "--debug"]
    parser = build_parser(argv)
    args, extra = parser.parse_known_args(argv)
    # key=value settings may also follow options (`finetune RECIPE --model M key=value`); argparse stops the
    # positional list at the first option, so collect the rest here
    stray = [a for a in extra if a.startswith("-") or "=" not in a or not hasattr(args, "settings")]
    if stray:
        parser.error(f"unrecognized arguments: {' '.join(stray)}")
    if extra:
        args.settings = [*args.settings, *extra]
    module = importlib.import_module(COMMANDS[args.command][0])
    prog = f"ttompc {args.command}"
    try:
        code = int(module.run(args) or 0)
        sys.stdout.flush()  # a closed pipe shows up here, inside the handlers, not at interpreter exit
        return code
    except UserError as err:
        if debug:
            raise
        _say(f"{prog}: error: {err}")
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        if debug:
            raise
        _say(f"\n{prog}: interrupted; {_resume_hint(module, args)}")
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # e.g. `ttompc zoo list | head`: the reader left, nothing to report
        _silence_stdout()
        return 128 + signal.SIGPIPE if hasattr(signal, "SIGPIPE") else 1
    except OSError as err:
        if debug or not (is_disk_full(err) or err.errno in _UNUSABLE_PATH):
            raise
        target = err.filename or _output_dir(module, args)
        if err.errno in _UNUSABLE_PATH:
            _say(
                f"{prog}: error: cannot use {target or 'a path'} ({(err.strerror or str(err)).lower()}); choose a "
                "location you can write to, or fix its permissions"
            )
            return EXIT_USER_ERROR
        where = f" while writing {target}" if target else ""
        _say(f"{prog}: error: no space left on device{where}. Free some space, then {_resume_hint(module, args)}")
        return 1
    except Exception as err:
        if debug or type(err).__name__ != "SafetensorError":
            raise
        _say(
            f"{prog}: error: a model file is damaged or not a safetensors file ({err}); "
            "re-download it (`ttompc zoo download NAME`) or re-export the bundle"
        )
        return EXIT_USER_ERROR


def is_disk_full(err: BaseException) -> bool:
    """True for an ENOSPC/EDQUOT ``OSError`` (pyarrow's IO errors carry the text but not always the errno)."""
    return isinstance(err, OSError) and (
        err.errno in (errno.ENOSPC, errno.EDQUOT) or "No space left on device" in str(err)
    )


def _resume_hint(module: ModuleType, args: argparse.Namespace) -> str:
    """What to do next, e.g. "re-run the same command to resume (checkpoints in runs/x are kept)"."""
    hint_of = getattr(module, "resume_hint", None)
    return hint_of(args) if hint_of is not None else "run the command again (it keeps no partial results)"


def _output_dir(module: ModuleType, args: argparse.Namespace) -> str | None:
    """Where the command writes (``output_dir(args)`` of its module), to name the full disk when the error does not
    (pyarrow's and many libraries' write errors carry no file name)."""
    output_of = getattr(module, "output_dir", None)
    try:
        return output_of(args) if output_of is not None else None
    except UserError:
        return None


def _say(line: str) -> None:
    try:
        sys.stdout.flush()
    except (BrokenPipeError, ValueError):
        _silence_stdout()
    print(line, file=sys.stderr)


def _silence_stdout() -> None:
    """Point stdout at /dev/null so the interpreter's final flush does not report the broken pipe again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):
        pass


if __name__ == "__main__":
    raise SystemExit(main())
