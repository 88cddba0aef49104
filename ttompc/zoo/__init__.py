"""The model zoo: cards in ``zoo/`` and verified downloads into a local cache (``Planner.from_pretrained`` in
``ttompc.policy`` loads a zoo model by name through ``download``), and the Hugging Face Hub: models and datasets
published to ``hf://`` repositories and models loaded from them through the Hugging Face cache (``hub``).

A published model is a *bundle*: ``model.safetensors`` (weights) + ``config.json`` (model config, scenario,
normalisation statistics, recipe, code version), published with the card's ``metrics.json`` (every number of the
card, under the command that measured it), each listed in the card with its URL, sha256 and size.
Importing this package does not import torch or Lightning.
"""

from __future__ import annotations

from pathlib import Path

from ttompc.zoo.cache import BundleError, UnsafePathError, cache_root, check_bundle
from ttompc.zoo.cards import CardError, ModelCard
from ttompc.zoo.download import download_bundle
from ttompc.zoo.errors import ChecksumError, DownloadError, PublishError
from ttompc.zoo.hub import download_model, is_hub_ref
from ttompc.zoo.publish import publish, publish_dataset, publish_to_hub
from ttompc.zoo.registry import UnknownModelError, get_card, load_cards, zoo_path


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
    "download_model",
    "is_hub_ref",
    "list_models",
    "model_info",
    "publish",
    "publish_dataset",
    "publish_to_hub",
]
