"""Publishing a model bundle: copy its two files to a destination, hash them, write the card and the index.

The zoo stores bundles and never builds a model (``ttompc.policy`` imports the zoo to load names, not the reverse):
a Lightning checkpoint is converted by the caller (``ttompc zoo publish`` does). Only ``model.safetensors`` and
``config.json`` are published. Card fields come from the bundle's ``config.json``
(``scenario: {name, version}``, ``model`` = architecture, and optionally ``kind``, ``recipe``, ``data_card``,
``code_version``) over an existing card's hand-edited fields (body, licence, tags, recipe, ...), and explicit
``card_fields`` over both.
"""

from __future__ import annotations

import hashlib
import json
import os
import urllib.parse
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ttompc.errors import UserError
from ttompc.version import code_version
from ttompc.zoo.cache import check_bundle
from ttompc.zoo.cards import (
    REQUIRED_FILES,
    FileEntry,
    ModelCard,
    read_card,
    render_card,
    validate_metrics,
    validate_name,
)
from ttompc.zoo.download import local_path
from ttompc.zoo.registry import write_index, zoo_path

DEFAULT_TAGS = ("ttompc", "trajectory-optimization", "mpc")
Evaluate = Callable[[Path], dict[str, dict[str, Any]]]


class PublishError(UserError, RuntimeError):
    """A publish request that cannot be carried out as asked."""


def publish(
    source: str | Path,
    name: str,
    to: str,
    *,
    zoo_dir: str | Path | None = None,
    metrics: dict[str, dict[str, Any]] | None = None,
    skip_eval: bool = False,
    evaluate: Evaluate | None = None,
    base_url: str | None = None,
    card_fields: dict[str, Any] | None = None,
) -> ModelCard:
    """Publish the bundle dir ``source`` as ``name`` into ``to``; returns the new card.

    ``to`` is a local directory or ``file://`` URL. Card URLs are relative when ``to`` lies inside the zoo dir
    (models shipped with the repository), ``base_url + filename`` when the files will be uploaded there by hand,
    else ``file://``. Metrics: ``metrics`` if given, else ``evaluate(bundle_dir)`` (the standard evaluation hook),
    else nothing with ``skip_eval``; a card never silently claims metrics it was not given.
    """
    validate_name(name)
    zoo = zoo_path(zoo_dir)
    dest = _destination(to)
    card_path = zoo / f"{name}.md"
    previous = _read_existing(card_path)
    bundle = _bundle_dir(Path(source))
    from_config = _from_config(check_bundle(bundle))
    if metrics is None and not skip_eval:
        if evaluate is None:
            raise PublishError(
                "no metrics: pass metrics (--card-metrics FILE) or skip_eval (--skip-eval); the "
                "standard evaluation is not wired into publish yet"
            )
        metrics = evaluate(bundle)
    metrics = validate_metrics(metrics or {})
    dest.mkdir(parents=True, exist_ok=True)
    files = []
    for filename in REQUIRED_FILES:
        sha256, size = _copy_hashed(bundle / filename, dest / filename)
        files.append(FileEntry(filename, _url_for(dest / filename, zoo, base_url), sha256, size))
    fields: dict[str, Any] = {"name": name, "kind": "TTO", "license": "MIT", "tags": list(DEFAULT_TAGS)}
    if previous is not None:  # keep what a maintainer edited by hand; metrics and files are replaced
        fields.update(
            kind=previous.kind,
            license=previous.license,
            tags=previous.tags,
            recipe=previous.recipe,
            data_card=previous.data_card,
            headline_metrics=[m for m in previous.headline_metrics if m in metrics],
        )
    fields.update({k: v for k, v in from_config.items() if v})
    fields.update(metrics=metrics, files=[f.to_dict() for f in files], **(card_fields or {}))
    card = ModelCard.from_dict(fields, body=previous.body if previous else "")
    card.body = card.body or _default_body(card)
    zoo.mkdir(parents=True, exist_ok=True)
    tmp = card_path.with_name(f".{card_path.name}.tmp")
    tmp.write_text(render_card(card), encoding="utf-8")
    os.replace(tmp, card_path)
    write_index(zoo)
    return card


def _from_config(config: dict[str, Any]) -> dict[str, Any]:
    scenario, model = config.get("scenario"), config.get("model")
    if not isinstance(scenario, dict) or not {"name", "version"} <= set(scenario) or not isinstance(model, dict):
        raise PublishError(
            "the bundle's config.json needs 'scenario': {'name', 'version'} and 'model' (the "
            "architecture config) to fill the card"
        )
    return {
        "kind": config.get("kind"),
        "scenario": {"name": scenario["name"], "version": scenario["version"]},
        "architecture": model,
        # Planner bundles store the recipe's content; the card wants its path (pass it via card_fields).
        "recipe": config["recipe"] if isinstance(config.get("recipe"), str) else "",
        "data_card": config.get("data_card"),
        "code_version": str(config.get("code_version") or code_version()),
    }


def _bundle_dir(source: Path) -> Path:
    if source.is_dir():
        return source
    if source.is_file() and source.suffix == ".ckpt":
        raise PublishError(
            f"{source} is a Lightning checkpoint, not a bundle directory",
            "convert it with Planner.from_pretrained(CKPT).save(DIR), or publish it with `ttompc zoo publish`",
        )
    raise PublishError(f"{source} is neither a bundle directory nor a Lightning .ckpt file")


def _destination(to: str) -> Path:
    scheme = urllib.parse.urlsplit(to).scheme
    if scheme == "file":
        return local_path(to, None)
    if scheme and not Path(to).is_absolute():
        raise PublishError(
            f"cannot publish to {to!r}: write to a local directory or file:// URL, upload the files "
            "yourself and pass base_url (--base-url) so the card points at them"
        )
    return Path(to)


def _copy_hashed(src: Path, dst: Path) -> tuple[str, int]:
    """Copy through a temporary file (so ``dst`` is never half-written) while hashing what is written."""
    digest, size = hashlib.sha256(), 0
    tmp = dst.with_name(f".{dst.name}.tmp")
    with open(src, "rb") as fin, open(tmp, "wb") as fout:
        for chunk in iter(lambda: fin.read(1 << 20), b""):
            fout.write(chunk)
            digest.update(chunk)
            size += len(chunk)
    os.replace(tmp, dst)
    return digest.hexdigest(), size


def _url_for(path: Path, zoo: Path, base_url: str | None) -> str:
    if base_url:
        return f"{base_url.rstrip('/')}/{path.name}"
    resolved, zoo_resolved = path.resolve(), zoo.resolve()
    if resolved.is_relative_to(zoo_resolved):
        return resolved.relative_to(zoo_resolved).as_posix()
    return resolved.as_uri()


def _read_existing(card_path: Path) -> ModelCard | None:
    return read_card(card_path) if card_path.is_file() else None


def _default_body(card: ModelCard) -> str:
    return (
        f"\n# {card.name}\n\n"
        f"{card.kind} model for the `{card.scenario}` scenario (version {card.scenario_version}).\n\n"
        "```python\nfrom ttompc.policy import Planner\n\n"
        f'planner = Planner.from_pretrained("{card.name}")\n```\n\n'
        "Card format, metric definitions and download details: [README.md](README.md).\n"
    )


def load_metrics(path: str | Path) -> dict[str, dict[str, Any]]:
    """Metrics from a JSON file ``{name: {value, how, ...}}`` (``--card-metrics``)."""
    with open(path, encoding="utf-8") as fh:
        return validate_metrics(json.load(fh))
