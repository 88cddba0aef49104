"""The zoo directory: model cards (``<name>.md``, the source of truth) and the generated ``index.json``.

The default zoo is the repository's ``zoo/``; ``$TTOMPC_ZOO`` or an explicit ``zoo_dir`` points elsewhere (an
installed wheel does not ship the cards, a fork may keep its own).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from ttompc.errors import UserError
from ttompc.zoo.cards import ModelCard, read_card, validate_name

INDEX_FILE = "index.json"
INDEX_FORMAT = 2  # 2: evaluations {name: {command, what, metrics}} in place of metrics {key: {value, how}}
_NOT_CARDS = {"readme.md"}


class UnknownModelError(UserError, KeyError):
    """A model name with no card in the zoo."""

    def __str__(self) -> str:  # KeyError would print the message with quotes around it
        return str(self.args[0])


def default_zoo_dir() -> Path:
    if os.environ.get("TTOMPC_ZOO"):
        return Path(os.environ["TTOMPC_ZOO"]).expanduser()
    return Path(__file__).resolve().parents[2] / "zoo"


def zoo_path(zoo_dir: str | Path | None) -> Path:
    return default_zoo_dir() if zoo_dir is None else Path(zoo_dir)


def load_cards(zoo_dir: str | Path | None = None) -> dict[str, ModelCard]:
    """All cards of the zoo, by name (sorted)."""
    root = zoo_path(zoo_dir)
    paths = sorted(p for p in root.glob("*.md") if p.name.lower() not in _NOT_CARDS)
    return {card.name: card for card in map(read_card, paths)}


def get_card(name: str, zoo_dir: str | Path | None = None) -> ModelCard:
    validate_name(name)
    path = zoo_path(zoo_dir) / f"{name}.md"
    if not path.is_file():
        available = ", ".join(load_cards(zoo_dir)) or "none"
        raise UnknownModelError(f"no model {name!r} in the zoo at {zoo_path(zoo_dir)} (available: {available})")
    return read_card(path)


def build_index(cards: dict[str, ModelCard]) -> dict[str, Any]:
    return {"format": INDEX_FORMAT, "models": [cards[name].to_dict() for name in sorted(cards)]}


def render_index(zoo_dir: str | Path | None = None) -> str:
    return json.dumps(build_index(load_cards(zoo_dir)), indent=2, ensure_ascii=False) + "\n"


def write_index(zoo_dir: str | Path | None = None) -> Path:
    """Regenerate ``index.json`` from the cards (atomically, so readers never see half a file)."""
    path = zoo_path(zoo_dir) / INDEX_FILE
    tmp = path.with_name(f".{INDEX_FILE}.tmp")
    tmp.write_text(render_index(zoo_dir), encoding="utf-8")
    os.replace(tmp, path)
    return path


def index_is_current(zoo_dir: str | Path | None = None) -> bool:
    path = zoo_path(zoo_dir) / INDEX_FILE
    return path.is_file() and path.read_text(encoding="utf-8") == render_index(zoo_dir)
