"""Every command a zoo card prints to reproduce its numbers runs as printed.

The commands are read from the cards (each evaluation's ``command`` and the ``ttompc evaluate`` lines of the body's
bash blocks), so the test follows the cards. The fast test checks that they name only models of the zoo; the slow one
runs each through the real CLI in a subprocess with smoke settings appended (a later ``key=value`` wins) and two
workers, so the process pool, where a withdrawn model once made these commands start failing workers forever, is
exercised.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from ttompc.zoo import list_models

REPO = Path(__file__).resolve().parents[1]
ZOO = REPO / "zoo"

# the smoke variant of each evaluation: settings appended to the card's command line
SMOKE: dict[str, list[str]] = {
    "warmstart": ["problems=2", "workers=2", "oracle_detours=0"],
    "mpc": ["problems=2", "workers=2", "max_steps=2", "plants=[nominal]"],
}


def card_commands() -> list[tuple[str, list[str]]]:
    """(card name, argv) of every distinct reproduce command of every card, in card order."""
    found: dict[tuple[str, ...], str] = {}
    for card in list_models(ZOO):
        lines = [evaluation["command"] for evaluation in card.evaluations.values()]
        for block in re.findall(r"```bash\n(.*?)```", card.body, re.DOTALL):
            lines += [line for line in block.splitlines() if line.startswith("ttompc evaluate ")]
        for line in lines:
            found.setdefault(tuple(shlex.split(line)), card.name)
    return [(name, list(argv)) for argv, name in found.items()]


COMMANDS = card_commands()


def _models(argv: list[str]) -> list[str]:
    """The models a command names (``--model X``, ``--ft-model X``, ``model=X``, ``ft_model=X``)."""
    flags = [argv[i + 1] for i, a in enumerate(argv[:-1]) if a in ("--model", "--ft-model")]
    return flags + [a.split("=", 1)[1] for a in argv if a.startswith(("model=", "ft_model="))]


def test_cards_print_reproduce_commands_that_name_only_zoo_models() -> None:
    zoo = {card.name for card in list_models(ZOO)}
    assert {name for name, _ in COMMANDS} == zoo, "every card prints the commands behind its numbers"
    for name, argv in COMMANDS:
        assert argv[:2] == ["ttompc", "evaluate"] and argv[2] in SMOKE, (name, argv)
        missing = [m for m in _models(argv) if m not in zoo]
        assert not missing, f"{name}'s card prints `{shlex.join(argv)}`, which names {missing}, not in the zoo"


def test_cards_print_the_command_the_reports_settings_give() -> None:
    """Each card command is the one reproduce command (``ttompc.evaluation.reproduce.report_command``) of the
    settings it sets, as the report records them (the scenario resolved from the model, inert settings set): the
    ``command`` that ``ttompc evaluate`` writes into its report and ``ttompc zoo metrics`` copies onto the card."""
    from ttompc.cli import build_parser
    from ttompc.commands.evaluate import _FLAGS
    from ttompc.config import command_config, to_container
    from ttompc.evaluation.closed_loop import ClosedLoopConfig
    from ttompc.evaluation.reproduce import report_command
    from ttompc.evaluation.warmstart import WarmStartConfig

    for name, argv in COMMANDS:
        kind = argv[2]
        args = build_parser(argv[1:]).parse_args(argv[1:])
        command = ClosedLoopConfig if kind == "mpc" else WarmStartConfig
        cfg = command_config(command, args, _FLAGS)
        recorded = {**to_container(cfg), "scenario": name.split("-")[0], "workers": 1, "out": "report"}
        assert report_command(kind, recorded, command()) == " ".join(argv), name


@pytest.mark.slow
@pytest.mark.parametrize(("card", "argv"), COMMANDS, ids=[f"{name}-{argv[2]}" for name, argv in COMMANDS])
def test_card_command_runs(card: str, argv: list[str], tmp_path: Path) -> None:
    env = {
        **os.environ,
        "TTOMPC_ZOO": str(ZOO),
        "TTOMPC_HOME": str(tmp_path / "cache"),
        "TTOMPC_PROGRESS": "0",
        "HF_HUB_OFFLINE": "1",
    }
    env.pop("TTOMPC_DEBUG", None)
    cmd = [sys.executable, "-m", "ttompc.cli", *argv[1:], *SMOKE[argv[2]], f"out={tmp_path / 'out'}"]
    res = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, f"{card}: {shlex.join(argv)}\n{res.stdout[-2000:]}\n{res.stderr[-4000:]}"
    assert (tmp_path / "out" / f"{argv[2]}.json").is_file()
