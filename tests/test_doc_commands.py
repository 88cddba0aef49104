"""Every ``ttompc`` command the docs show still runs as written.

The commands are parsed from the fenced code blocks of README.md, docs/*.md and the model cards (zoo/*.md): a line
that starts with ``ttompc`` (after ``$ `` or ``VAR=value`` environment prefixes, ``\\`` continuations joined,
``$VAR`` taken from a ``VAR=value`` line of the same block, optional ``[...]`` parts included). Each one runs in
process through ``ttompc.cli.main`` with ``--print-config`` added, which builds and validates its whole config
(recipe, shortcut flags, ``key=value`` settings, the protocol's ``mpc.KEY`` settings) and stops before any work: an
unknown or removed setting is exit status 2 and fails here. Commands without ``--print-config`` (listed below) are
parsed by their argument parser instead, so a removed flag fails too.
"""

from __future__ import annotations

import argparse
import re
import shlex
from pathlib import Path

import pytest

from ttompc.cli import COMMANDS, build_parser, main

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), *sorted((ROOT / "zoo").glob("*.md"))]

# subcommands that take --print-config (their command lines run with it) ...
PRINT_CONFIG = {
    "solve",
    "generate",
    "train",
    "finetune",
    "demo",
    "check-scenario",
    "evaluate warmstart",
    "evaluate mpc",
    "evaluate target",
    "evaluate loss",
}
# ... and those that do not (their command lines are only parsed): every subcommand is in one of the two
PARSE_ONLY = {
    "evaluate compare",
    "zoo list",
    "zoo info",
    "zoo download",
    "zoo publish",
    "zoo metrics",
    "zoo index",
}
NESTED = ("evaluate", "zoo")  # subcommands with actions of their own

FENCE = re.compile(r"^```[^\n]*\n(.*?)^```", re.DOTALL | re.MULTILINE)
ASSIGNMENT = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)=(\S+)$")


def doc_commands() -> list[tuple[str, list[str]]]:
    """``(where, argv)`` of every ``ttompc`` command line in the docs' code blocks, argv[0] == "ttompc"."""
    found = []
    for path in DOCS:
        text = path.read_text(encoding="utf-8")
        for block in FENCE.finditer(text):
            first_line = text.count("\n", 0, block.start(1)) + 1
            variables: dict[str, str] = {}
            for offset, line in enumerate(block.group(1).replace("\\\n", " \n").splitlines()):
                line = line.strip().removeprefix("$ ")
                if match := ASSIGNMENT.match(line):
                    variables[match.group(1)] = match.group(2)
                    continue
                try:
                    tokens = shlex.split(line, comments=True)
                except ValueError:  # not shell (YAML, Python): no command here
                    continue
                while tokens and ASSIGNMENT.match(tokens[0]):  # OMP_NUM_THREADS=1 ttompc ...
                    tokens = tokens[1:]
                if not tokens or tokens[0] != "ttompc":
                    continue
                argv = []
                for token in tokens:
                    for name, value in variables.items():
                        token = token.replace(f"${{{name}}}", value).replace(f"${name}", value)
                    optional = re.fullmatch(r"\[(.+)\]", token)  # `[--check]`, `[protocol=zoo]`: check it too
                    argv.append(optional.group(1) if optional else token)
                found.append((f"{path.relative_to(ROOT)}:{first_line + offset}", argv))
    return found


def subcommand(argv: list[str]) -> str:
    """``evaluate mpc``, ``zoo list``, ``train``, ...; "" for a bare ``ttompc``."""
    return " ".join(argv[1:3]) if argv[1:2] and argv[1] in NESTED else " ".join(argv[1:2])


COMMAND_LINES = doc_commands()


def test_the_docs_show_commands_of_every_kind() -> None:
    """The extraction finds the docs' commands (the README's and the cards' at least) and knows each subcommand."""
    kinds = {subcommand(argv) for _, argv in COMMAND_LINES}
    assert len(COMMAND_LINES) > 50, COMMAND_LINES
    assert {"generate", "train", "finetune", "evaluate warmstart", "evaluate mpc", "zoo publish"} <= kinds, kinds
    unknown = [f"{w}: {shlex.join(a)}" for w, a in COMMAND_LINES if subcommand(a) not in PRINT_CONFIG | PARSE_ONLY]
    assert not unknown, "a subcommand this test does not know; add it to PRINT_CONFIG or PARSE_ONLY:\n" + "\n".join(
        unknown
    )


def test_print_config_refuses_a_removed_setting(capsys: pytest.CaptureFixture[str]) -> None:
    """What the command-line check relies on: --print-config validates the settings (``mpc.finish`` was removed)."""
    assert _run(["evaluate", "mpc", "--scenario", "freeflyer", "mpc.rtg_mode=value", "--print-config"]) == 0
    assert _run(["evaluate", "mpc", "--scenario", "freeflyer", "mpc.finish=1.0", "--print-config"]) == 2
    assert "unknown setting 'finish'" in capsys.readouterr().err


def test_the_lists_match_the_cli() -> None:
    """PRINT_CONFIG and PARSE_ONLY are every subcommand of the CLI, split by whether it takes --print-config."""
    names = {name for name in COMMANDS if name not in NESTED}
    for name in NESTED:
        names |= {f"{name} {action}" for action in _subparsers(_parser_of([name])).choices}
    assert PRINT_CONFIG | PARSE_ONLY == names, names ^ (PRINT_CONFIG | PARSE_ONLY)
    assert not PRINT_CONFIG & PARSE_ONLY
    for name in sorted(names):
        options = {option for action in _parser_of(name.split())._actions for option in action.option_strings}
        assert ("--print-config" in options) == (name in PRINT_CONFIG), name


def _subparsers(parser: argparse.ArgumentParser) -> argparse._SubParsersAction:
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return sub


def _parser_of(argv: list[str]) -> argparse.ArgumentParser:
    """The parser of a subcommand (``["zoo", "list"]``), its arguments added as ``ttompc`` adds them."""
    parser = build_parser(argv)
    for word in argv:
        parser = _subparsers(parser).choices[word]
    return parser


@pytest.mark.parametrize(("where", "argv"), COMMAND_LINES, ids=[where for where, _ in COMMAND_LINES])
def test_doc_command_runs(
    where: str, argv: list[str], monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(ROOT)  # the docs' relative paths (recipes/, examples/) are the repository's
    command = shlex.join(argv)
    if subcommand(argv) in PRINT_CONFIG:
        code = _run([*argv[1:], "--print-config"])
        assert code == 0, f"{where}: `{command}` fails with --print-config:\n{capsys.readouterr().err[-2000:]}"
    else:
        parser = build_parser(argv[1:])
        try:
            parser.parse_args(argv[1:])
        except SystemExit:
            pytest.fail(f"{where}: `{command}` does not parse:\n{capsys.readouterr().err[-2000:]}")


def _run(argv: list[str]) -> int:
    try:
        return main(argv)
    except SystemExit as exit_:  # argparse: an unknown flag or a missing argument
        return int(exit_.code or 0)
