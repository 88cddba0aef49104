"""Streaming ``LightningDataModule`` over open-loop datasets and DAgger shard folders.

Per-row streaming and ``datasets``' own shuffle/interleave are much slower than
``IterableDataset.with_format("numpy").iter(batch)`` (measured in docs/design.md). So each source is read in column
batches, rows are shuffled in an in-memory pool per source, sources are mixed per batch
(binomial open-loop count), shard order is permuted every pass, and shards are split by rank and DataLoader
worker here (``.iter`` does not split by itself).

Batch contract (float32 unless stated, normalised with the open-loop dataset's train-split ``NormStats``):
    states (B, L, n)            x_t, t in the window (from x_0..x_{N−1})
    actions (B, L, m)           u_t
    goals (B, L, n)             goal repeated over the window
    rtg (B, L, 1), ctg (B, L, 1)
    timesteps (B, L) int64      absolute step indices t
    target_actions (B, L, m)    normalised like actions
    target_next_states (B, L, n) normalised like states
    mask (B, L)                 1 for steps with a target (DAgger rows: NaN targets mark unlabelled steps, 0 here)
    value_grad (B, L, n)        the value output's target gradient d rtg/d s in normalised units, from the costates
    grad_mask (B, L)            1 where the row has a costate (0: none, value_grad 0)
    source (B,) int64           0 rel, 1 scp, 2 dagger (``schema.SOURCE_CODES``)
    problem_id (B,) int64
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from ttompc.config import from_container, to_container
from ttompc.data.config import DataConfig
from ttompc.data.distributed import rank_info
from ttompc.data.manifests import open_loop_manifests
from ttompc.data.schema import SOURCE_CODES
from ttompc.data.shards import SPLITS, ShardError, verify_shard
from ttompc.policy.stats import NormStats
from ttompc.scenarios import find_scenario

COLUMNS = ("problem_id", "source", "states", "actions", "goal", "rtg", "ctg", "target_actions", "target_next_states")
OPTIONAL = ("costates",)  # read where a shard has them, NaN (no target) where it was written before them
Chunk = dict[str, np.ndarray]
_OPENED: dict[tuple[str, bool], Any] = {}  # streaming datasets per (shard path, open-loop columns)


def _read_file(path: str, read_batch: int, allowed: frozenset[str]) -> Iterator[Chunk]:
    """Column batches of one shard through ``datasets``' fast path, keeping rows whose source is allowed.

    Open-loop rows have targets = (actions, states[1:]) by construction, so for them the two target columns are
    derived instead of read (less decoding)."""
    import datasets
    import pyarrow.parquet as pq

    open_loop = "dagger" not in allowed
    columns = [c for c in COLUMNS if not (open_loop and c.startswith("target_"))]
    try:
        present = set(pq.read_schema(path).names)
        columns += [c for c in OPTIONAL if c in present]
        ds = _OPENED.get((path, open_loop))
        if ds is None:  # the parquet reader decodes only ``columns``; opened once per process and reused
            ds = datasets.load_dataset("parquet", data_files=[path], split="train", streaming=True, columns=columns)
            ds = _OPENED[(path, open_loop)] = ds.with_format("arrow")
        chunks = map(_to_numpy, ds.iter(read_batch))
    except (pa.ArrowException, OSError) as err:
        raise ShardError(f"shard file {path} is unreadable (truncated or corrupt): {err}") from None
    while True:
        try:  # only next() inside the try: a generator closed at its yield must not reach the handler
            chunk = next(chunks)
        except StopIteration:
            return
        except (pa.ArrowException, OSError) as err:
            raise ShardError(f"shard file {path} is unreadable (truncated or corrupt): {err}") from None
        keep = np.isin(chunk["source"], list(allowed))
        if keep.any():
            chunk = {k: v[keep] for k, v in chunk.items()}
            if "costates" not in chunk:
                chunk["costates"] = np.full_like(chunk["states"], np.nan)
            if open_loop:
                chunk["target_actions"], chunk["target_next_states"] = chunk["actions"], chunk["states"][:, 1:]
            yield chunk


def _to_numpy(table: pa.Table) -> Chunk:
    """Arrow batch -> numpy without per-row Python work: fixed-shape nested lists are flattened to their value
    buffer and reshaped (faster than ``with_format("numpy")`` for our 2-D arrays; docs/design.md)."""
    out = {}
    for name in table.column_names:
        arr = table.column(name).combine_chunks()
        if isinstance(arr.type, pa.ExtensionType):  # datasets' Array2D wraps list<list<float>>
            arr = arr.storage
        shape = []
        while pa.types.is_list(arr.type) or pa.types.is_fixed_size_list(arr.type):
            lengths = arr.value_lengths().to_numpy(zero_copy_only=False)
            shape.append(int(lengths[0]) if len(lengths) else 0)
            arr = arr.flatten()
        out[name] = arr.to_numpy(zero_copy_only=False).reshape(len(table), *shape)
    return out


def _assign(files: list[str], consumer: int, n_consumers: int) -> tuple[list[str], int | None]:
    """Files of one (rank, worker) consumer: whole files when there are enough, else every file with a row
    filter ``problem_id % n_consumers == consumer`` (returned as the stride residue) so splits stay disjoint."""
    if len(files) >= n_consumers:
        return files[consumer::n_consumers], None
    return files, consumer


def _stream(
    files: list[str],
    read_batch: int,
    allowed: frozenset[str],
    residue: int | None,
    n_consumers: int,
    rng: np.random.Generator | None,
) -> Iterator[Chunk]:
    """One pass over ``files`` (permuted when ``rng`` is given)."""
    order = [files[i] for i in rng.permutation(len(files))] if rng is not None else files
    for path in order:
        for chunk in _read_file(path, read_batch, allowed):
            if residue is not None:
                keep = chunk["problem_id"] % n_consumers == residue
                chunk = {k: v[keep] for k, v in chunk.items()}
            if len(chunk["problem_id"]):
                yield chunk


class _ShufflePool:
    """Holds up to ``size`` rows of an endless chunk stream; ``take(k)`` returns k random rows and refills
    their slots from the stream, so every row is drawn once per pass in a well-mixed order."""

    def __init__(self, chunks: Iterator[Chunk], size: int, rng: np.random.Generator, what: str) -> None:
        self.chunks, self.rng = chunks, rng
        self.pending: Chunk = {}
        self.pool = self._next_rows(size, what)

    def _next_rows(self, k: int, what: str = "") -> Chunk:
        parts, have = [self.pending] if self.pending else [], len(self.pending.get("problem_id", ()))
        while have < k:
            chunk = next(self.chunks, None)
            if chunk is None:
                if not have:
                    raise ShardError(f"no rows to stream for {what}")
                break
            parts.append(chunk)
            have += len(chunk["problem_id"])
        rows = {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}
        self.pending = {c: v[k:] for c, v in rows.items()}
        return {c: v[:k] for c, v in rows.items()}

    def take(self, k: int) -> Chunk:
        idx = self.rng.choice(len(self.pool["problem_id"]), size=k, replace=False)
        out = {c: v[idx] for c, v in self.pool.items()}
        fresh = self._next_rows(k)
        for c in self.pool:
            self.pool[c][idx] = fresh[c]
        return out


class _Batcher:
    """Rows -> the batch contract: context windows, normalisation, torch tensors."""

    def __init__(self, stats: NormStats, n_steps: int, context_length: int | None) -> None:
        """``context_length`` None: the whole horizon, whatever the scenario's N."""
        L = n_steps if context_length is None else context_length
        if not 1 <= L <= n_steps:
            raise ValueError(f"context_length must be in [1, {n_steps}] (the datasets' horizon), got {L}")
        self.stats, self.N, self.L = stats, n_steps, L

    def __call__(self, rows: Chunk, starts: np.ndarray) -> dict[str, torch.Tensor]:
        B, N, Lc, st = len(rows["problem_id"]), self.N, self.L, self.stats
        t = starts[:, None] + np.arange(Lc)[None]  # (B, L)

        def win(a: np.ndarray) -> np.ndarray:
            a = a[:, :N]
            if Lc == N:  # full trajectories: no gather needed
                return a
            return np.take_along_axis(a, t.reshape(B, Lc, *([1] * (a.ndim - 2))), axis=1)

        f32 = np.float32
        # DAgger rows mark unlabelled steps with NaN targets: no loss there (mask 0, target 0)
        target_a, target_s = win(rows["target_actions"]).astype(f32), win(rows["target_next_states"]).astype(f32)
        labelled = np.isfinite(target_a).all(axis=-1) & np.isfinite(target_s).all(axis=-1)  # (B, L)
        # the value's target gradient d v/d s in normalised units: −(σ_s/σ_rtg)·λ_t (v: the normalised rtg)
        lam = win(rows["costates"]).astype(f32)
        known = np.isfinite(lam).all(axis=-1)  # (B, L)
        sd_s, sd_r = st.mean_std("states", lam)[1], st.mean_std("rtg", lam[..., :1])[1]
        out = {
            "states": st.normalize("states", win(rows["states"]).astype(f32)),
            "actions": st.normalize("actions", win(rows["actions"]).astype(f32)),
            "goals": np.repeat(st.normalize("goals", rows["goal"].astype(f32))[:, None], Lc, axis=1),
            "rtg": st.normalize("rtg", win(rows["rtg"]).astype(f32)[..., None]),
            "ctg": st.normalize("ctg", win(rows["ctg"]).astype(f32)[..., None]),
            "timesteps": t.astype(np.int64),
            "target_actions": np.nan_to_num(st.normalize("actions", target_a), nan=0.0),
            "target_next_states": np.nan_to_num(st.normalize("states", target_s), nan=0.0),
            "mask": labelled.astype(f32),
            "value_grad": np.nan_to_num(-lam * sd_s / sd_r, nan=0.0),
            "grad_mask": known.astype(f32),
            "source": np.array([SOURCE_CODES[s] for s in rows["source"]], dtype=np.int64),
            "problem_id": rows["problem_id"].astype(np.int64),
        }
        return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in out.items()}


def _consumer(rank: int, world_size: int) -> tuple[int, int, int]:
    info = get_worker_info()
    wid, nw = (info.id, info.num_workers) if info is not None else (0, 1)
    return rank * nw + wid, world_size * nw, wid


class TrainStream(IterableDataset):
    """Endless mixed stream of training batches (or ``batches`` per epoch, equal on every rank and worker)."""

    def __init__(
        self,
        ol_files: list[str],
        cl_files: list[str],
        cfg: DataConfig,
        batcher: _Batcher,
        p_open_loop: float,
        rank: int,
        world_size: int,
    ) -> None:
        self.ol_files, self.cl_files, self.cfg, self.batcher = ol_files, cl_files, cfg, batcher
        self.p_open_loop, self.rank, self.world_size = p_open_loop, rank, world_size
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def _endless(
        self, files: list[str], allowed: frozenset[str], c: int, n: int, rng: np.random.Generator
    ) -> Iterator[Chunk]:
        """Passes over this consumer's files, shard order permuted each pass. A source no larger than the
        shuffle pool (early DAgger iterations) is kept in memory after the first pass instead of re-read."""
        mine, residue = _assign(files, c, n)
        cache: list[Chunk] | None = []
        rows = 0
        for chunk in _stream(mine, self.cfg.read_batch_size, allowed, residue, n, rng):
            rows += len(chunk["problem_id"])
            cache = cache if cache is not None and rows <= self.cfg.shuffle_pool else None
            if cache is not None:
                cache.append(chunk)
            yield chunk
        if not rows:
            return  # nothing for this consumer: the shuffle pool reports it
        while True:
            if cache is not None:
                yield from (cache[i] for i in rng.permutation(len(cache)))
            else:
                yield from _stream(mine, self.cfg.read_batch_size, allowed, residue, n, rng)

    def __iter__(self) -> Iterator[dict[str, torch.Tensor]]:
        cfg = self.cfg
        c, n, wid = _consumer(self.rank, self.world_size)
        rng = np.random.default_rng([cfg.seed, self.epoch, self.rank, wid])
        allowed = frozenset(("rel", "scp") if cfg.sources == "both" else (cfg.sources,))
        pool = max(cfg.shuffle_pool, cfg.batch_size)
        ol = _ShufflePool(self._endless(self.ol_files, allowed, c, n, rng), pool, rng, "open-loop data")
        cl = (
            _ShufflePool(self._endless(self.cl_files, frozenset(("dagger",)), c, n, rng), pool, rng, "DAgger data")
            if self.cl_files and self.p_open_loop < 1
            else None
        )
        budget = None
        if cfg.train_batches_per_epoch is not None:
            nw = n // self.world_size
            budget = cfg.train_batches_per_epoch // nw + (wid < cfg.train_batches_per_epoch % nw)
        B, span = cfg.batch_size, self.batcher.N - self.batcher.L + 1
        while budget is None or budget > 0:
            k = B if cl is None else int(rng.binomial(B, self.p_open_loop))
            parts = [ol.take(k)] if k else []
            if k < B:
                assert cl is not None  # k < B only when there is a closed-loop pool
                parts.append(cl.take(B - k))
            rows = {col: np.concatenate([p[col] for p in parts]) for col in parts[0]}
            yield self.batcher(rows, rng.integers(0, span, size=B))
            if budget is not None:
                budget -= 1


class EvalStream(IterableDataset):
    """One deterministic pass over a split: fixed file order, fixed windows (start from the problem id)."""

    def __init__(
        self, files: list[str], allowed: frozenset[str], cfg: DataConfig, batcher: _Batcher, rank: int, world_size: int
    ) -> None:
        self.files, self.allowed, self.cfg, self.batcher = files, allowed, cfg, batcher
        self.rank, self.world_size = rank, world_size

    def __iter__(self) -> Iterator[dict[str, torch.Tensor]]:
        c, n, _ = _consumer(self.rank, self.world_size)
        mine, residue = _assign(self.files, c, n)
        B, span = self.cfg.eval_batch_size or self.cfg.batch_size, self.batcher.N - self.batcher.L + 1
        buf: list[Chunk] = []
        have = 0
        chunks = _stream(mine, self.cfg.read_batch_size, self.allowed, residue, n, None)
        for chunk in itertools.chain(chunks, [None]):
            if chunk is not None:
                buf.append(chunk)
                have += len(chunk["problem_id"])
            while have >= B or (chunk is None and have > 0):
                rows = {col: np.concatenate([p[col] for p in buf]) for col in buf[0]}
                batch = {col: v[:B] for col, v in rows.items()}
                buf, have = [{col: v[B:] for col, v in rows.items()}], max(have - B, 0)
                starts = (batch["problem_id"] * 7919 + np.isin(batch["source"], ["scp"])) % span
                yield self.batcher(batch, starts)


class _EpochLoader(DataLoader):
    """Tells the stream which epoch starts before workers are spawned (Lightning only calls ``set_epoch`` on
    samplers), so each epoch draws a new shard order and shuffle."""

    def __iter__(self) -> Any:
        self.dataset.set_epoch(self.dataset.epoch + 1)  # type: ignore[attr-defined]
        return super().__iter__()


class TrajectoryDataModule(L.LightningDataModule):
    """Streams the batch contract above from ``DataConfig.paths`` (open loop) and ``DataConfig.dagger_dirs``.

    After ``setup``: ``stats`` (the first open-loop dataset's train-split NormStats, also used for DAgger rows),
    ``scenario_name``, ``n_steps``, ``manifest``. DAgger folders can be appended to ``cfg.dagger_dirs`` between
    fits; nothing is rewritten.
    """

    def __init__(self, cfg: DataConfig | dict[str, Any]) -> None:
        super().__init__()
        self.cfg = cfg if isinstance(cfg, DataConfig) else from_container(DataConfig, cfg)
        # kept in checkpoints, not logged: the module logs the whole recipe, data section included, and Lightning
        # refuses to log two hparams of one name (this config's ``scenario`` None, "any", vs the module's data scenario)
        self.save_hyperparameters(to_container(self.cfg), logger=False)
        self.stats: NormStats | None = None
        self.scenario_name: str | None = None
        self.n_steps: int | None = None
        self.manifest: dict[str, Any] | None = None
        self._files: dict[str, list[str]] = {}
        self._dagger: dict[str, list[str]] = {}

    def setup(self, stage: str | None = None) -> None:
        if self.manifest is not None:
            # training calls setup("fit") to build the model from the stats, then Lightning calls it again: the
            # config is fixed per instance, so reading manifests and hashing every shard once is enough
            return
        cfg = self.cfg
        if not cfg.paths:
            raise ValueError("DataConfig.paths must name at least one open-loop dataset folder")
        manifests = open_loop_manifests(cfg)
        self.manifest = manifests[0]
        self.scenario_name, self.n_steps = self.manifest["scenario"]["name"], self.manifest["scenario"]["n_steps"]
        # load the scenario from its recorded spec, so that its name resolves in this process (user scenarios)
        find_scenario(self.scenario_name, self.manifest["scenario"].get("spec"))
        self.stats = NormStats.from_dict(self.manifest["norm_stats"])
        self._files = {s: [] for s in SPLITS}
        for root, m in zip(cfg.paths, manifests, strict=True):
            for shard in m["shards"]:
                for f in shard["files"]:
                    path = Path(root) / f["path"]
                    if cfg.verify_checksums:
                        verify_shard(path, f["sha256"])
                    self._files[f["split"]].append(str(path))
        self._dagger = {
            s: sorted(str(p) for d in cfg.dagger_dirs for p in (Path(d) / s).glob("*.parquet")) for s in SPLITS
        }
        self._batcher = _Batcher(self.stats, self.n_steps, cfg.context_length)

    def use_stats(self, stats: NormStats) -> None:
        """Normalise with ``stats`` instead of the first dataset's own: a model continued on new data keeps the
        input scaling its weights were trained with."""
        if self.manifest is None or self.n_steps is None:
            raise RuntimeError("TrajectoryDataModule.use_stats needs setup() first")
        self.stats = stats
        self._batcher = _Batcher(stats, self.n_steps, self.cfg.context_length)

    @property
    def _ranks(self) -> tuple[int, int]:
        trainer = self.trainer  # set by Lightning under fit/validate/test: authoritative for DDP ranks
        if trainer is not None:
            return trainer.global_rank, trainer.world_size
        info = rank_info()
        return info.rank, info.world_size

    def open_loop_fraction(self) -> float:
        """Probability that a training row is open-loop ("fixed" ratio, or the reference's growing CL share)."""
        cfg, dirs = self.cfg, self.cfg.dagger_dirs
        if not self._dagger.get("train"):
            return 1.0
        if cfg.closed_loop_share == "fixed":
            return cfg.open_loop_fraction

        def rows(d: str) -> int:
            return sum(pq.ParquetFile(p).metadata.num_rows for p in (Path(d) / "train").glob("*.parquet"))

        r = cfg.open_loop_fraction / (1.0 - cfg.open_loop_fraction)
        last, total = rows(dirs[-1]), sum(rows(d) for d in dirs)
        return r * last / (r * last + total)

    def _loader(self, ds: IterableDataset, loader_cls: type[DataLoader] = DataLoader) -> DataLoader:
        return loader_cls(ds, batch_size=None, num_workers=self.cfg.num_workers)

    def train_dataloader(self) -> DataLoader:
        rank, world = self._ranks
        ds = TrainStream(
            self._files["train"], self._dagger["train"], self.cfg, self._batcher, self.open_loop_fraction(), rank, world
        )
        return self._loader(ds, _EpochLoader)

    def eval_dataloader(self, split: str, closed_loop: bool = False) -> DataLoader:
        """One deterministic pass (``EvalStream``) over ``split`` ("train", "val" or "test") of the open-loop
        datasets (their rows of ``sources``) or, with ``closed_loop``, of the DAgger folders; ``ShardError`` when
        it has no rows."""
        if closed_loop:
            if not self._dagger.get(split):
                raise ShardError(f"no {split}/*.parquet in DAgger folders {self.cfg.dagger_dirs}")
            files, allowed = self._dagger[split], frozenset(("dagger",))
        else:
            if not self._files[split]:
                raise ShardError(f"split {split!r} of {self.cfg.paths} has no rows")
            files = self._files[split]
            allowed = frozenset(("rel", "scp") if self.cfg.sources == "both" else (self.cfg.sources,))
        return self._loader(EvalStream(files, allowed, self.cfg, self._batcher, *self._ranks))

    def val_dataloader(self) -> DataLoader:
        return self.eval_dataloader("val")

    def test_dataloader(self) -> DataLoader:
        return self.eval_dataloader("test")

    def dagger_val_dataloader(self) -> DataLoader:
        """The DAgger folders' ``val`` shards (the reference's closed-loop validation set)."""
        return self.eval_dataloader("val", closed_loop=True)
