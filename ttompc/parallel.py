"""Process-pool helpers shared by data generation, DAgger collection and evaluation."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@contextlib.contextmanager
def single_threaded_env() -> Iterator[None]:
    """Spawned workers inherit the environment: one BLAS/OpenMP thread each, so a pool of one worker per core does
    not oversubscribe the machine. Variables the user set are kept; ours are removed again afterwards."""
    old = {k: os.environ.get(k) for k in _THREAD_VARS}
    for k in _THREAD_VARS:
        os.environ.setdefault(k, "1")
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
