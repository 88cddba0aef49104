"""Typed configs of the data pipeline (OmegaConf structured dataclasses; see ``ttompc.config.load_config``).

``GenerateConfig`` fully determines a generated dataset: the same config gives the same rows, whatever the number
of workers or ranks and however often the run was interrupted. ``DataConfig`` is what training and DAgger read.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

Sources = Literal["rel", "scp", "both"]
ClosedLoopShare = Literal["fixed", "grow"]


@dataclass
class SplitConfig:
    """Fractions of *problems* per split; REL and SCP rows of one problem always share a split (no leakage)."""

    train: float = 0.9
    val: float = 0.05
    test: float = 0.05
    salt: int = 0  # changes the assignment without changing the problems

    def fractions(self) -> dict[str, float]:
        fr = {"train": self.train, "val": self.val, "test": self.test}
        if any(v < 0 for v in fr.values()) or abs(sum(fr.values()) - 1.0) > 1e-9:
            raise ValueError(f"split fractions must be non-negative and sum to 1, got {fr}")
        return fr


@dataclass
class GenerateConfig:
    scenario: str = "freeflyer"
    problems: int = 20_000
    out: str = "data/freeflyer-v1"
    seed: int = 0  # root seed; problem i uses SeedSequence(seed, spawn_key=(i,))
    shard_size: int = 500  # problems per shard (a fixed contiguous id range)
    workers: int = 0  # 0 = all cores
    solver: str = "ttompc.solvers.scp:solve_problem"  # "module:function" with solve_problem's signature
    backend: str | None = None  # convex backend passed to the solver (None = solver default)
    max_shards: int | None = None  # stop after writing this many shards (chunked runs; resume later)
    finalize_wait_s: float = 0.0  # rank 0 waits this long for other ranks' shards before the manifest
    splits: SplitConfig = field(default_factory=SplitConfig)
    name: str | None = None  # dataset name for the card (default: the output folder name)
    card_dir: str | None = None  # the card is <out>/README.md; set this to also copy it to <card_dir>/<name>.md

    def __post_init__(self) -> None:
        if self.problems < 1 or self.shard_size < 1:
            raise ValueError(f"problems and shard_size must be at least 1, got {self.problems} and {self.shard_size}")


@dataclass
class DataConfig:
    """What the ``TrajectoryDataModule`` streams.

    Batches mix open-loop rows (``sources`` of ``paths``) with DAgger rows (``dagger_dirs``) at
    ``open_loop_fraction`` ("fixed"), or with the reference's growing closed-loop share ("grow": open-loop weight
    r·|newest DAgger dir| against all DAgger rows, r = f/(1−f), i.e. 9:1 at the first iteration then growing).
    """

    paths: list[str] = field(default_factory=list)  # open-loop dataset folders (one manifest each)
    # the scenario the recipe is written for (recipes/<scenario>/ set it): every dataset must hold its trajectories,
    # or a quadrotor recipe would train on free-flyer data without a word; None accepts any one scenario
    scenario: str | None = None
    dagger_dirs: list[str] = field(default_factory=list)  # DAgger shard folders (``train/*.parquet``)
    sources: Sources = "both"
    open_loop_fraction: float = 0.9
    closed_loop_share: ClosedLoopShare = "fixed"
    batch_size: int = 64
    eval_batch_size: int | None = None  # default: batch_size
    num_workers: int = 0
    shuffle_pool: int = 4096  # rows held per source for in-memory shuffling
    read_batch_size: int = 256  # rows per ``IterableDataset.iter`` read
    context_length: int | None = None  # L ≤ N, random windows of length L when L < N; None: the whole horizon N
    train_batches_per_epoch: int | None = None  # None: one endless epoch (use max_steps); else equal per rank
    verify_checksums: bool = True  # sha256 of every open-loop shard against its manifest at setup
    seed: int = 0
