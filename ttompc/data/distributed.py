"""Rank and world size from the launcher's environment (torchrun or SLURM), without initialising torch.distributed,
so that dataset generation can be split across ranks by environment alone."""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass


@dataclass(frozen=True)
class RankInfo:
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def rank_info(env: Mapping[str, str] | None = None) -> RankInfo:
    """torchrun's RANK/WORLD_SIZE/LOCAL_RANK take precedence over SLURM_PROCID/SLURM_NTASKS/SLURM_LOCALID."""
    env = os.environ if env is None else env
    for rank_key, world_key, local_key in (
        ("RANK", "WORLD_SIZE", "LOCAL_RANK"),
        ("SLURM_PROCID", "SLURM_NTASKS", "SLURM_LOCALID"),
    ):
        if rank_key in env and world_key in env:
            info = RankInfo(int(env[rank_key]), int(env[world_key]), int(env.get(local_key, 0)))
            if not (0 <= info.rank < info.world_size):
                raise ValueError(f"{rank_key}={info.rank} is outside [0, {world_key}={info.world_size})")
            return info
    return RankInfo()


def strided(items: list, rank: int, world_size: int) -> list:
    """The disjoint slice of ``items`` owned by ``rank`` (every world_size-th item): complete over all ranks."""
    return items[rank::world_size]
