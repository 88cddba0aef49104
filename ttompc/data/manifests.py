"""Reading datasets written by ``ttompc generate``: their ``manifest.json`` (``load_manifest``), and the checks that
the open-loop datasets of a recipe exist, are finished, are of one scenario and fit the recipe (``check_datasets``,
``open_loop_manifests``), made from the manifests alone before a command creates, imports or computes anything."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ttompc.config import ConfigError
from ttompc.data.config import DataConfig
from ttompc.data.resumable import META_DIR
from ttompc.data.shards import ShardError
from ttompc.errors import UserError

MANIFEST = "manifest.json"


class ManifestError(UserError, ShardError):
    """A dataset's ``manifest.json`` that is missing, damaged or lacks what readers take."""


def load_manifest(root: str | Path) -> dict[str, Any]:
    """The manifest of the dataset ``root``, with the keys every reader takes (``scenario`` with its ``name`` and
    ``n_steps``); raises ``ManifestError`` in one line for a missing, damaged or incomplete one."""
    path = Path(root) / MANIFEST
    if not path.is_file():
        raise ManifestError(f"{path} not found: not a finalised dataset (run `ttompc generate ... --finalize`)")
    redo = "re-run `ttompc generate ... --finalize` with the dataset's settings to rewrite it"
    try:
        manifest = json.loads(path.read_text())
        int(manifest["scenario"]["n_steps"]), str(manifest["scenario"]["name"])  # what every reader takes
    except (ValueError, UnicodeDecodeError) as err:
        raise ManifestError(f"{path} is damaged (not JSON: {err})", redo) from None
    except (KeyError, TypeError):
        raise ManifestError(f"{path} is incomplete: it names no scenario with its n_steps", redo) from None
    return manifest


def open_loop_manifests(cfg: DataConfig) -> list[dict[str, Any]]:
    """The manifests of ``cfg.paths``, checked against each other and against the recipe before anything trains on
    them: one scenario and horizon in every folder, the recipe's ``data.scenario`` when it names one, and a
    ``data.context_length`` within the horizon. Raises ``ConfigError`` (one line, naming the folders)."""
    manifests = [load_manifest(p) for p in cfg.paths]
    first = manifests[0]["scenario"]
    name, steps = first["name"], first["n_steps"]
    for path, manifest in zip(cfg.paths[1:], manifests[1:], strict=True):
        other = manifest["scenario"]
        if (other["name"], other["n_steps"]) != (name, steps):
            raise ConfigError(
                f"data.paths mixes scenarios: {cfg.paths[0]} holds {name} trajectories of {steps} steps, {path} "
                f"{other['name']} trajectories of {other['n_steps']} steps",
                "train on datasets of one scenario",
            )
    if cfg.scenario is not None and cfg.scenario != name:
        raise ConfigError(
            f"the recipe is for {cfg.scenario} (data.scenario) but {cfg.paths[0]} holds {name} trajectories",
            f"train a recipe of recipes/{name}/ on it, or point data.paths at {cfg.scenario} data",
        )
    if cfg.context_length is not None and not 1 <= cfg.context_length <= steps:
        raise ConfigError(
            f"data.context_length={cfg.context_length} does not fit the {steps}-step {name} trajectories of "
            f"{cfg.paths[0]}",
            f"set data.context_length within [1, {steps}]",
        )
    return manifests


def check_datasets(cfg: DataConfig) -> list[dict[str, Any]]:
    """Every dataset folder of ``cfg`` exists, is a finished ``ttompc generate`` dataset and fits the recipe
    (``open_loop_manifests``): checked from the manifests alone (no shard is read), before a command creates,
    imports or computes anything. Returns the manifests of ``cfg.paths``; raises ``ConfigError`` (one line naming the
    folder and what to do)."""
    paths, dagger_dirs = cfg.paths, cfg.dagger_dirs
    if not paths and not dagger_dirs:
        raise ConfigError(
            "no training data: data.paths is empty (the recipe leaves it to the command line)",
            "pass data.paths=[FOLDER], a dataset written by `ttompc generate`",
        )
    for key, folders in (("data.paths", paths), ("data.dagger_dirs", dagger_dirs)):
        missing = [p for p in folders if not Path(p).is_dir()]
        if missing:
            what = "is a file, not a dataset folder" if Path(missing[0]).exists() else "does not exist"
            raise ConfigError(
                f"{key}: dataset folder {missing[0]} {what}",
                f"make it with `ttompc generate out={missing[0]} ...` or point {key}=[...] at existing folders",
            )
    for folder in map(Path, paths):
        if (folder / MANIFEST).is_file():
            continue
        if (folder / META_DIR).is_dir():
            raise ConfigError(
                f"data.paths: the generation of {folder} is not finished (no {MANIFEST})",
                "re-run the same `ttompc generate` command (add --finalize once every rank's shards exist)",
            )
        raise ConfigError(
            f"data.paths: {folder} is not a dataset made by `ttompc generate` (no {MANIFEST})",
            "point data.paths=[...] at a folder written by `ttompc generate`",
        )
    return open_loop_manifests(cfg) if paths else []
