"""The zoo directory: model cards (``<name>.md``, the source of truth, each with the metrics file its ``files`` lists;
shipped models keep theirs beside their bundles in ``models/<name>/``) and the generated ``index.json``.

The default zoo is the repository's ``zoo/``; ``$TTOMPC_ZOO`` or an explicit ``zoo_dir`` points elsewhere (an
installed wheel does not ship the cards, a fork may keep its own).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from ttompc.errors import UserError
from ttompc.zoo.cards import CardError, ModelCard, load_evaluations, read_card, validate_name
from ttompc.zoo.download import read_published

INDEX_FILE = "index.json"
INDEX_FORMAT = 3  # 3: evaluations names the metrics file; 2: evaluations {name: {command, what, metrics}} inline
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


def read_evaluations(card: ModelCard, zoo: Path) -> ModelCard:
    """``card``, of the zoo at ``zoo``, with its evaluations read from its metrics file (a relative URL resolves
    against ``zoo``, a remote one is fetched into the cache first) and checked against the card
    (``load_evaluations``); a card without a metrics file as it is."""
    entry = card.evaluations_entry
    return card if entry is None else load_evaluations(card, read_published(entry, zoo))


def load_card(path: Path) -> ModelCard:
    """The zoo card at ``path`` (``<zoo>/<name>.md``) with its evaluations (``read_evaluations``)."""
    card = read_card(path)
    try:
        return read_evaluations(card, path.parent)
    except CardError as err:
        raise CardError(f"{path}: {err}") from None


def _card_paths(zoo_dir: str | Path | None) -> list[Path]:
    return sorted(p for p in zoo_path(zoo_dir).glob("*.md") if p.name.lower() not in _NOT_CARDS)


def load_cards(zoo_dir: str | Path | None = None) -> dict[str, ModelCard]:
    """All cards of the zoo with their evaluations, by name (sorted); a zoo folder that does not exist (a
    ``$TTOMPC_ZOO`` or ``zoo_dir`` that points at nothing) is a ``UserError``, not an empty zoo."""
    folder = zoo_path(zoo_dir)
    if not folder.is_dir():
        via = "$TTOMPC_ZOO" if zoo_dir is None and os.environ.get("TTOMPC_ZOO") else "the zoo folder"
        raise UserError(f"no zoo at {folder} ({via} does not exist)", "point it at a folder of model cards")
    return {card.name: card for card in map(load_card, _card_paths(zoo_dir))}


def get_card(name: str, zoo_dir: str | Path | None = None) -> ModelCard:
    validate_name(name)
    path = zoo_path(zoo_dir) / f"{name}.md"
    if not path.is_file():
        available = ", ".join(load_cards(zoo_dir)) or "none"
        raise UnknownModelError(f"no model {name!r} in the zoo at {zoo_path(zoo_dir)} (available: {available})")
    return load_card(path)


def build_index(cards: dict[str, ModelCard]) -> dict[str, Any]:
    return {"format": INDEX_FORMAT, "models": [cards[name].to_dict() for name in sorted(cards)]}


def render_index(zoo_dir: str | Path | None = None) -> str:
    """``index.json``'s text: the cards' front matter, which names their metrics files (not read here: a card
    published with ``--base-url`` is indexed before its files are uploaded)."""
    cards = {card.name: card for card in map(read_card, _card_paths(zoo_dir))}
    return json.dumps(build_index(cards), indent=2, ensure_ascii=False) + "\n"


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
