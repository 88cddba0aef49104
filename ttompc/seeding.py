"""Every random draw in ttompc starts from a seed derived here, from a root seed and a spawn key, never the clock.

One derivation, ``SeedSequence(root, spawn_key=key)`` → its first 64-bit word, shifted to a non-negative 63-bit
int (so it fits an int64 parquet column and ``numpy.random.default_rng``). Each use has its own stream, a spawn-key
prefix that makes its seeds disjoint from the others' whatever root seeds they use:

* dataset problem i: ``(i,)`` (no prefix; the key the published datasets were generated with);
* evaluation problem i, attempt a: ``(EVAL_STREAM, i, a)`` — held out from every dataset;
* DAgger rollout r of iteration i: ``(DAGGER_STREAM, i, r)``.

Seeds depend only on (root, key), so a problem or rollout is the same whatever the number of workers or ranks and
however often a run was resumed. The values are pinned by tests: changing them silently changes every dataset and
evaluation set.
"""

from __future__ import annotations

import numpy as np

EVAL_STREAM = 0x6576616C  # "eval"
DAGGER_STREAM = 0x64616767  # "dagg"


def derive_seed(root: int, *key: int) -> int:
    """The 63-bit seed of spawn key ``key`` under ``root``: ``SeedSequence(root, spawn_key=key)``'s first word >> 1."""
    state = np.random.SeedSequence(root, spawn_key=key).generate_state(1, dtype=np.uint64)[0]
    return int(state >> np.uint64(1))


def rng(root: int, *key: int) -> np.random.Generator:
    """``default_rng(derive_seed(root, *key))``."""
    return np.random.default_rng(derive_seed(root, *key))


def problem_seed(root: int, problem_id: int) -> int:
    """Seed of dataset problem ``problem_id`` (``SeedSequence(root).spawn``'s child ``problem_id``)."""
    return derive_seed(root, problem_id)


def eval_seed(root: int, index: int, attempt: int = 0) -> int:
    """Seed of attempt ``attempt`` at evaluation problem ``index`` (a stream disjoint from the datasets)."""
    return derive_seed(root, EVAL_STREAM, index, attempt)


def rollout_seed(root: int, iteration: int, index: int) -> int:
    """Seed of DAgger rollout ``index`` of iteration ``iteration`` (problem, horizon and expert windows)."""
    return derive_seed(root, DAGGER_STREAM, iteration, index)
