"""The model zoo: cards in ``zoo/``, verified downloads into a local cache, and ``load_pretrained``.

A published model is a *bundle*: ``model.safetensors`` (weights) + ``config.json`` (model config, scenario,
normalisation statistics, recipe, code version), each listed in the card with its URL, sha256 and size.
Importing this package does not import torch or Lightning.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from ttompc.zoo.cache import BundleError, UnsafePathError, cache_root, check_bundle
from ttompc.zoo.cards import CardError, ModelCard, validate_name
from ttompc.zoo.download import ChecksumError, DownloadError, download_bundle
from ttompc.zoo.publish import PublishError, publish
from ttompc.zoo.registry import UnknownModelError, get_card, load_cards, zoo_path

if TYPE_CHECKING:
    from ttompc.planner import Planner


def list_models(zoo_dir: str | Path | None = None) -> list[ModelCard]:
    """Cards of all models in the zoo, sorted by name."""
    return list(load_cards(zoo_dir).values())


def model_info(name: str, zoo_dir: str | Path | None = None) -> ModelCard:
    return get_card(name, zoo_dir)


def download(
    name: str, cache_dir: str | Path | None = None, *, zoo_dir: str | Path | None = None, progress: bool = True
) -> Path:
    """Fetch and verify the files of ``name``; returns the local bundle dir (files already cached are reused)."""
    return download_bundle(get_card(name, zoo_dir), zoo_path(zoo_dir), cache_dir, progress)


def load_pretrained(
    name_or_path: str | Path,
    *,
    cache_dir: str | Path | None = None,
    zoo_dir: str | Path | None = None,
    progress: bool = True,
) -> Planner:
    """A ``Planner`` from a local bundle dir (checked first) or a zoo model name (downloaded if needed).

    The bundle is validated with safetensors before ``Planner.load`` sees it, so weights are never unpickled.
    """
    path = Path(name_or_path)
    if path.is_dir():
        bundle = path
    else:
        try:
            validate_name(str(name_or_path))
        except CardError:
            raise BundleError(f"{name_or_path!r} is neither a bundle directory nor a zoo model name") from None
        bundle = download(str(name_or_path), cache_dir, zoo_dir=zoo_dir, progress=progress)
    check_bundle(bundle)
    try:
        from ttompc.planner import Planner
    except ImportError as err:
        raise ImportError(f"loading a pretrained model needs ttompc.planner ({err})") from err
    return Planner.load(bundle)


__all__ = [
    "BundleError",
    "CardError",
    "ChecksumError",
    "DownloadError",
    "ModelCard",
    "PublishError",
    "UnknownModelError",
    "UnsafePathError",
    "cache_root",
    "check_bundle",
    "download",
    "list_models",
    "load_pretrained",
    "model_info",
    "publish",
]
