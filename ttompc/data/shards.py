"""Parquet shards written through Hugging Face ``datasets``, atomically, with sha256 checksums.

``write_shard`` / ``ShardWriter`` are the one way rows reach disk (open-loop generation and DAgger alike), so every
shard carries the same ``datasets`` features in its parquet metadata. A shard is written to a temporary file in
the same folder, fsynced and renamed: readers and resumed runs never see half a shard. ``read_shard`` turns any
corruption (checksum mismatch, truncated file, bad footer) into a ``ShardError`` that names the file.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import signal
import tempfile
import threading
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from datasets import Dataset, Features
from datasets.table import InMemoryTable

SPLITS = ("train", "val", "test")


class ShardError(RuntimeError):
    """A shard that is missing, truncated, corrupt or does not match its manifest."""


@dataclass(frozen=True)
class ShardInfo:
    path: str  # relative to the dataset root
    rows: int
    sha256: str

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def sha256_file(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _replace_atomically(tmp: Path, path: Path) -> None:
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _tmp_path(path: Path) -> Path:
    """A fresh temporary file next to ``path`` with the mode a plain ``open`` would give (0666 & ~umask):
    ``mkstemp`` creates 0600, which the rename would carry over to the final file."""
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_umask())
    finally:
        os.close(fd)
    return Path(name)


def atomic_write_text(path: str | Path, text: str) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_path(path)
    try:
        tmp.write_text(text)
        _replace_atomically(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_json(path: str | Path, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True) + "\n")


def rows_to_columns(rows: Sequence[dict[str, Any]], features: Features) -> dict[str, Any]:
    """Row dicts -> stacked columns in feature order (missing or extra keys are errors)."""
    names = list(features)
    for i, r in enumerate(rows):
        if set(r) != set(names):
            missing, extra = sorted(set(names) - set(r)), sorted(set(r) - set(names))
            raise ValueError(f"row {i} does not match the schema: missing {missing}, unexpected {extra}")
    cols: dict[str, Any] = {}
    for k in names:
        values = [r[k] for r in rows]
        cols[k] = values if isinstance(values[0], str) else np.stack([np.asarray(v) for v in values])
    return cols


@contextlib.contextmanager
def interrupt_after() -> Iterator[None]:
    """Hold a Ctrl-C (SIGINT) that arrives inside the block until the block ends, then raise ``KeyboardInterrupt``.
    An interrupt landing inside pyarrow's or datasets' callbacks surfaces as an unrelated error (a features mismatch,
    exit 1) instead of the interrupt a resumable command reports; held, it leaves a whole shard. Only the main
    thread receives signals: elsewhere the block runs as is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous if previous is not None else signal.default_int_handler)
    if caught:
        raise KeyboardInterrupt


def write_shard(rows: Sequence[dict[str, Any]], path: str | Path, features: Features) -> int:
    """Write ``rows`` (see ``schema.make_row``) to the parquet file ``path`` atomically; returns the row count. A
    Ctrl-C during the write is raised once the shard is complete (``interrupt_after``)."""
    if not rows:
        raise ValueError(f"refusing to write an empty shard {path}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with interrupt_after():
        # the table carries the ``datasets`` features in its schema metadata; pyarrow's own writer (a context
        # manager) is closed even when an exception lands mid-write, where ``Dataset.to_parquet`` left a writer
        # whose finaliser printed a traceback at exit
        table = Dataset.from_dict(rows_to_columns(rows, features), features=features).data.table
        tmp = _tmp_path(path)
        try:
            pq.write_table(table, str(tmp))
            _replace_atomically(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
    return len(rows)


class ShardWriter:
    """Writes numbered shards ``<root>/<split>/<prefix>-<index:05d>.parquet`` and returns their ``ShardInfo``.

    The DAgger pipeline writes its shards with this class (``source="dagger"`` rows from ``schema.make_row``), so
    a DAgger folder is read by the DataModule exactly like an open-loop one.
    """

    def __init__(self, root: str | Path, features: Features, prefix: str = "shard") -> None:
        self.root = Path(root)
        self.features = features
        self.prefix = prefix

    def path(self, split: str, index: int) -> Path:
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        return self.root / split / f"{self.prefix}-{index:05d}.parquet"

    def write(self, rows: Sequence[dict[str, Any]], index: int, split: str = "train") -> ShardInfo:
        path = self.path(split, index)
        n = write_shard(rows, path, self.features)
        return ShardInfo(path=str(path.relative_to(self.root)), rows=n, sha256=sha256_file(path))


def verify_shard(path: str | Path, sha256: str | None) -> None:
    """Raise ``ShardError`` naming ``path`` if it is missing or its checksum differs from ``sha256``."""
    path = Path(path)
    if not path.is_file():
        raise ShardError(f"shard file {path} is missing")
    if sha256 is not None and (actual := sha256_file(path)) != sha256:
        raise ShardError(
            f"shard file {path} is corrupt: sha256 {actual[:12]}… does not match the manifest "
            f"({sha256[:12]}…); regenerate it (re-run `ttompc generate` with the same arguments)"
        )


def read_table(path: str | Path, sha256: str | None = None) -> pa.Table:
    """The shard's arrow table, checked against ``sha256`` when given; corruption -> ``ShardError``."""
    verify_shard(path, sha256)
    try:
        return pq.read_table(path)
    except (pa.ArrowException, OSError) as err:
        raise ShardError(f"shard file {path} is unreadable (truncated or corrupt): {err}") from None


def read_shard(path: str | Path, sha256: str | None = None) -> Dataset:
    """The shard as an in-memory ``datasets.Dataset`` with its stored features (no cache files written)."""
    return Dataset(InMemoryTable(read_table(path, sha256)))
