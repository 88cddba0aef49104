"""Typed configs of the data pipeline (OmegaConf structured dataclasses; see ``ttompc.config.load_config``).

``GenerateConfig`` fully determines a generated dataset: the same config gives the same rows, whatever the number
of workers or ranks and however often the run was interrupted. ``DataConfig`` is what training and DAgger read.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from ttompc.ranges import Checked, setting

Sources = Literal["rel", "scp", "both"]
ClosedLoopShare = Literal["fixed", "grow"]


@dataclass
class SplitConfig(Checked):
    """Fractions of *problems* per split, each in [0, 1], summing to 1; REL and SCP rows of one problem always share
    a split (no leakage)."""

    train: float = setting(0.9, ge=0, le=1)
    val: float = setting(0.05, ge=0, le=1)
    test: float = setting(0.05, ge=0, le=1)
    salt: int = setting(0)  # changes the assignment without changing the problems

    def __post_init__(self) -> None:
        super().__post_init__()
        total = self.train + self.val + self.test
        if abs(total - 1.0) > 1e-9:
            raise ValueError(
                f"invalid splits: train + val + test must sum to 1, got {self.train:g} + {self.val:g} + "
                f"{self.test:g} = {total:g}"
            )

    def fractions(self) -> dict[str, float]:
        return {"train": self.train, "val": self.val, "test": self.test}


@dataclass
class GenerateConfig(Checked):
    scenario: str = "freeflyer"
    problems: int = setting(20_000, ge=1)
    out: str = "data/freeflyer-v1"
    seed: int = setting(0, ge=0)  # root seed; problem i uses SeedSequence(seed, spawn_key=(i,))
    shard_size: int = setting(500, ge=1)  # problems per shard (a fixed contiguous id range)
    workers: int = setting(0, ge=0, per_core=4, meaning="0: all cores")
    solver: str = "ttompc.solvers.scp:solve_problem"  # "module:function" with solve_problem's signature
    backend: str | None = None  # convex backend passed to the solver (None = solver default)
    max_shards: int | None = setting(None, ge=1)  # stop after writing this many new shards (resume later); None: all
    finalize_wait_s: float = setting(0.0, ge=0)  # rank 0 waits this long for other ranks' shards before the manifest
    splits: SplitConfig = field(default_factory=SplitConfig)
    name: str | None = None  # dataset name for the card (default: the output folder name)
    card_dir: str | None = None  # the card is <out>/README.md; set this to also copy it to <card_dir>/<name>.md


@dataclass
class DataConfig(Checked):
    """What the ``TrajectoryDataModule`` streams.

    Batches mix open-loop rows (``sources`` of ``paths``) with DAgger rows (``dagger_dirs``) at
    ``open_loop_fraction`` ("fixed"), or with the reference's growing closed-loop share ("grow": open-loop weight
    r·|newest DAgger dir| against all DAgger rows, r = f/(1−f), i.e. 9:1 at the first iteration then growing).
    """

    paths: list[str] = setting(factory=list, unique=True)  # open-loop dataset folders (one manifest each)
    # the scenario the recipe is written for (recipes/<scenario>/ set it): every dataset must hold its trajectories,
    # or a quadrotor recipe would train on free-flyer data without a word; None accepts any one scenario
    scenario: str | None = None
    dagger_dirs: list[str] = setting(factory=list, unique=True)  # DAgger shard folders (``train/*.parquet``)
    sources: Sources = "both"
    open_loop_fraction: float = setting(0.9, ge=0, le=1)
    closed_loop_share: ClosedLoopShare = "fixed"
    batch_size: int = setting(64, ge=1)
    eval_batch_size: int | None = setting(None, ge=1)  # default: batch_size
    num_workers: int = setting(0, ge=0, per_core=4)
    shuffle_pool: int = setting(4096, ge=1)  # rows held per source for in-memory shuffling
    read_batch_size: int = setting(256, ge=1)  # rows per ``IterableDataset.iter`` read
    # L ≤ N, random windows of length L when L < N; None: the whole horizon N
    context_length: int | None = setting(None, ge=1)
    # None: one endless epoch (use max_steps); else equal per rank
    train_batches_per_epoch: int | None = setting(None, ge=1)
    verify_checksums: bool = True  # sha256 of every open-loop shard against its manifest at setup
    seed: int = setting(0, ge=0)
