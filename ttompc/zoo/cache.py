"""The local model cache: content-addressed blobs plus immutable per-model snapshot directories.

Layout under the cache root::

    blobs/sha256/<hex>                      verified file contents, read-only, named by their hash
    models/<name>/<snapshot>/<filename>     hard links (or copies) of blobs: the bundle dir that gets loaded

A snapshot id is derived from the card's (filename, sha256) pairs, so re-publishing a model under the same name
creates a new snapshot instead of rewriting files that a running process may have memory-mapped.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from ttompc.errors import UserError
from ttompc.zoo.cards import REQUIRED_FILES, FileEntry, validate_name, validate_sha256


class UnsafePathError(UserError, ValueError):
    """A path that would resolve outside the directory it must stay in."""


def cache_root(cache_dir: str | Path | None = None) -> Path:
    """Explicit ``cache_dir``, else ``$TTOMPC_HOME``, else ``$XDG_CACHE_HOME/ttompc``, else ``~/.cache/ttompc``."""
    if cache_dir is not None:
        return Path(cache_dir).expanduser()
    if os.environ.get("TTOMPC_HOME"):
        return Path(os.environ["TTOMPC_HOME"]).expanduser()
    if os.environ.get("XDG_CACHE_HOME"):
        return Path(os.environ["XDG_CACHE_HOME"]).expanduser() / "ttompc"
    return Path.home() / ".cache" / "ttompc"


def inside(root: Path, *parts: str) -> Path:
    """``root/parts...`` after resolving symlinks, refusing anything that lands outside ``root``."""
    base = root.resolve()
    path = base.joinpath(*parts).resolve()
    if not path.is_relative_to(base):
        raise UnsafePathError(f"{'/'.join(parts)!r} resolves to {path}, outside {base}")
    return path


def blob_path(root: Path, sha256: str) -> Path:
    return inside(root, "blobs", "sha256", validate_sha256(sha256))


def snapshot_id(files: Iterable[FileEntry]) -> str:
    pairs = sorted(f"{f.filename}\0{f.sha256}" for f in files)
    return hashlib.sha256("\n".join(pairs).encode()).hexdigest()[:16]


def assemble_bundle(root: Path, name: str, files: list[FileEntry]) -> Path:
    """The snapshot dir of ``name`` holding ``files`` (whose blobs must already be in the cache).

    Built in a temporary sibling and renamed into place, so a snapshot dir is either complete or absent.
    """
    target = inside(root, "models", validate_name(name), snapshot_id(files))
    if target.is_dir():
        if all(_same_file(blob_path(root, f.sha256), target / f.filename) for f in files):
            return target
        _discard_dir(target)  # a file was replaced or edited: rebuild from the verified blobs
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".staging-", dir=target.parent))
    try:
        for f in files:
            _link_or_copy(blob_path(root, f.sha256), inside(staging, validate_name(f.filename, "file name")))
        try:
            staging.rename(target)
        except OSError:
            if not target.is_dir():  # a concurrent process winning the race is fine; anything else is not
                raise
    finally:
        if staging.exists():
            shutil.rmtree(staging)
    return target


def _same_file(blob: Path, linked: Path) -> bool:
    """``linked`` is the (verified) blob itself, or a copy of it with the same bytes."""
    if not linked.is_file():
        return False
    if os.path.samefile(blob, linked):
        return True
    return blob.stat().st_size == linked.stat().st_size and sha256_file(blob) == sha256_file(linked)


def _discard_dir(path: Path) -> None:
    """Move ``path`` aside before deleting it, so a process that has its files open or mapped keeps them."""
    trash = Path(tempfile.mkdtemp(prefix=".trash-", dir=path.parent))
    os.replace(path, trash / "snapshot")
    shutil.rmtree(trash, ignore_errors=True)


def sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _link_or_copy(src: Path, dst: Path) -> None:
    """Hard link (no extra disk space), falling back to a copy on file systems without hard links."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


class BundleError(UserError, ValueError):
    """A directory that is not a loadable model bundle."""


CHECKSUMS = "sha256"  # config.json key: {file name: sha256} of the bundle's other files (``Planner.save``)
_REEXPORT = "re-export the bundle, or for a zoo model run `ttompc zoo download NAME` again"


def check_bundle(bundle_dir: str | Path, within: Path | None = None) -> dict[str, Any]:
    """Validate a bundle without executing anything in it; returns its parsed ``config.json``.

    Its files must resolve inside ``within`` (default: the bundle dir itself; a Hugging Face cache snapshot links
    its files to its repository folder's ``blobs/``, so the Hub download passes that folder).

    The files whose sha256 ``config.json`` records (``CHECKSUMS``; bundles saved before it existed have none) are
    re-hashed: flipped bytes in the weights would otherwise load silently and plan NaNs. ``model.safetensors`` is
    opened with safetensors (a header + raw tensors, no code), so a pickle or a torch checkpoint renamed to
    ``model.safetensors`` fails here with ``SafetensorError`` instead of being unpickled.
    """
    from safetensors import SafetensorError, safe_open

    bundle = Path(bundle_dir)
    missing = [f for f in REQUIRED_FILES if not (bundle / f).is_file()]
    if missing:
        raise BundleError(f"{bundle} is not a model bundle: missing {missing}")
    config_path = bundle / "config.json"
    try:
        config = json.loads(config_path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise BundleError(f"{config_path} is not valid JSON: {err}", _REEXPORT) from None
    if not isinstance(config, dict):
        raise BundleError(f"{config_path} must hold a JSON object")
    _verify_checksums(bundle, config.get(CHECKSUMS, {}), bundle if within is None else within)
    weights_path = bundle / "model.safetensors"
    try:
        with safe_open(weights_path, framework="numpy") as weights:
            if not list(weights.keys()):
                raise BundleError(f"{weights_path} holds no tensors")
    except SafetensorError as err:
        raise BundleError(f"{weights_path} is damaged or not a safetensors file ({err})", _REEXPORT) from None
    return config


def _verify_checksums(bundle: Path, recorded: object, within: Path) -> None:
    if not isinstance(recorded, dict) or not all(isinstance(v, str) for v in recorded.values()):
        raise BundleError(f"{bundle / 'config.json'}: {CHECKSUMS!r} must map file names to sha256 hex digests")
    for filename, expected in recorded.items():
        path = bundle / validate_name(filename, "file name")
        if not path.resolve().is_relative_to(within.resolve()):
            raise UnsafePathError(f"{path} resolves to {path.resolve()}, outside {within.resolve()}")
        if not path.is_file():
            raise BundleError(f"{path} is missing (config.json records its sha256)", _REEXPORT)
        actual = sha256_file(path)
        if actual != expected:
            raise BundleError(
                f"{path} is damaged: sha256 {actual[:16]}… differs from {expected[:16]}… recorded when the bundle "
                "was saved",
                _REEXPORT,
            )
