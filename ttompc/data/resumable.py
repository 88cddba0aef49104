"""``ShardedFolder``: the one resumable writer of numbered shards (open-loop generation and DAgger collection).

Items 0..total−1 (problems, rollouts) are cut into fixed shards: shard k always covers items [k·S, (k+1)·S). A shard
is written as one parquet file per non-empty split (``ShardWriter``, atomic) and then its metadata
``meta/shard-<k>.json`` (atomic), which lists each file with its sha256. A shard counts as *done* only when that
metadata exists, covers the same item range and every file it lists matches its checksum, so an interrupted run
resumes by skipping done shards and yields the shards of an uninterrupted run (the same rows when the producer's
rows depend only on the item, as generation's do up to their wall-clock timings). Under torchrun/SLURM rank r owns
the shards k ≡ r (mod world size).
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any, TypeVar

from datasets import Features

from ttompc.data.distributed import RankInfo, strided
from ttompc.data.shards import SPLITS, ShardError, ShardWriter, atomic_write_json, verify_shard

META_DIR = "meta"
T = TypeVar("T")


class ShardedFolder:
    """Shards of ``total`` items, ``shard_size`` per shard, under ``root`` (files ``<split>/<prefix>-<k>.parquet``)."""

    def __init__(self, root: str | Path, features: Features, total: int, shard_size: int, prefix: str = "shard"):
        if total <= 0 or shard_size <= 0:
            raise ValueError(f"item count and shard size must be positive, got {total}, {shard_size}")
        self.root = Path(root)
        self.total, self.shard_size = total, shard_size
        self.writer = ShardWriter(self.root, features, prefix=prefix)

    @property
    def n_shards(self) -> int:
        return -(-self.total // self.shard_size)

    def item_range(self, k: int) -> tuple[int, int]:
        """Items [start, stop) of shard ``k``."""
        return k * self.shard_size, min((k + 1) * self.shard_size, self.total)

    def meta_path(self, k: int) -> Path:
        return self.root / META_DIR / f"shard-{k:05d}.json"

    def meta(self, k: int) -> dict[str, Any]:
        return json.loads(self.meta_path(k).read_text())

    def done(self, k: int) -> bool:
        """Metadata for the same item range exists and every file it lists matches its checksum."""
        path = self.meta_path(k)
        if not path.is_file():
            return False
        meta = json.loads(path.read_text())
        if (meta.get("start"), meta.get("stop")) != self.item_range(k):
            return False
        try:
            for f in meta["files"]:
                verify_shard(self.root / f["path"], f["sha256"])
        except ShardError:
            return False
        return True

    def missing(self) -> list[int]:
        """Every shard (of any rank) that is not done."""
        return [k for k in range(self.n_shards) if not self.done(k)]

    def mine(self, ranks: RankInfo) -> list[int]:
        """The shards rank ``ranks.rank`` owns."""
        return strided(list(range(self.n_shards)), ranks.rank, ranks.world_size)

    def pending(self, ranks: RankInfo) -> list[int]:
        """The shards this rank owns that are not done yet, in order."""
        return [k for k in self.mine(ranks) if not self.done(k)]

    def items(self, shards: Sequence[int]) -> list[int]:
        """The item ids of ``shards``, in order (the task list of a run)."""
        return [i for k in shards for i in range(*self.item_range(k))]

    def beyond(self) -> list[str]:
        """Metadata files of shards past ``total`` (left by a run with more items)."""
        return sorted(
            p.name for p in (self.root / META_DIR).glob("shard-*.json") if int(p.stem.split("-")[1]) >= self.n_shards
        )

    def group(self, shards: Sequence[int], results: Iterable[T]) -> Iterator[tuple[int, list[T], float]]:
        """Cut ``results`` (one per item of ``shards``, in item order) into (shard, its results, seconds taken)."""
        it, t0 = iter(results), time.perf_counter()
        for k in shards:
            start, stop = self.item_range(k)
            batch = [next(it) for _ in range(stop - start)]
            yield k, batch, time.perf_counter() - t0
            t0 = time.perf_counter()

    def write(self, k: int, rows_by_split: dict[str, list[dict[str, Any]]], **meta: Any) -> dict[str, Any]:
        """Write shard ``k``: a file per non-empty split (stale files of empty splits removed), then its metadata
        ``{index, start, stop, files, **meta}``; returns the metadata."""
        unknown = set(rows_by_split) - set(SPLITS)
        if unknown:
            raise ValueError(f"unknown splits {sorted(unknown)}; expected a subset of {SPLITS}")
        self.meta_path(k).unlink(missing_ok=True)  # not done until the new metadata lands
        files = []
        for split in SPLITS:
            rows = rows_by_split.get(split, [])
            if rows:
                files.append({"split": split, **self.writer.write(rows, k, split).to_dict()})
            else:
                self.writer.path(split, k).unlink(missing_ok=True)  # a stale file from a run with other settings
        start, stop = self.item_range(k)
        out = {"index": k, "start": start, "stop": stop, "files": files, **meta}
        atomic_write_json(self.meta_path(k), out)
        return out

    def wait(self, timeout_s: float, poll_s: float = 5.0) -> bool:
        """Wait up to ``timeout_s`` for every shard (other ranks' too) to be done; True when they are."""
        deadline = time.monotonic() + timeout_s
        while self.missing():
            if time.monotonic() >= deadline:
                return False
            time.sleep(min(poll_s, max(timeout_s, 0.01)))
        return True
