"""The one process pool of ttompc (data generation, DAgger collection, evaluation) and its thread pinning.

``pool_map`` runs tasks inline for one worker and otherwise in a *spawn* pool: fresh interpreters inherit no RNG,
torch or solver state, so results depend only on the task (with ``ttompc.seeding``) and not on the worker count.
Each worker gets one BLAS/OpenMP thread (``single_threaded_env``) and one torch thread: a pool of one worker per
core then does not oversubscribe the machine, and batch-1 model rollouts, chains of tiny kernels, run fastest on one
thread (a 10-step rollout was 100x slower with 2 threads than with 1 on a shared 2-core machine).
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import signal
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any

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


@contextlib.contextmanager
def single_torch_thread() -> Iterator[None]:
    """One torch intra-op thread inside the block (batch-1 rollouts: extra OpenMP threads only spin-wait); the
    previous count is restored afterwards. Imports torch."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def _start_worker(
    scenarios: Sequence[str], pin_torch: bool, initializer: Callable[..., None] | None, initargs: tuple[Any, ...]
) -> None:
    """Runs once in each spawned worker: loads the parent's scenarios by spec (so their names resolve here too,
    whether built in, defined in a test module or loaded from a user's file), torch thread pin, then the caller's
    initializer."""
    if scenarios:
        from ttompc.scenarios import get_scenario

        for spec in scenarios:
            get_scenario(spec)
    if pin_torch:
        import torch

        torch.set_num_threads(1)
    if initializer is not None:
        initializer(*initargs)


def _start_pool_worker(*args: Any) -> None:
    """Ctrl-C reaches every process of the terminal's group: only the parent handles it (it stops the pool and
    says how to resume), so workers ignore it instead of each printing a traceback."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _start_worker(*args)


def pool_map(
    fn: Callable[[Any], Any],
    tasks: Iterable[Any],
    workers: int,
    initializer: Callable[..., None] | None = None,
    initargs: tuple[Any, ...] = (),
    *,
    scenarios: Sequence[str] = (),
    pin_torch: bool = True,
) -> Iterator[Any]:
    """``fn(task)`` for every task, yielded in task order as they finish.

    ``workers <= 1`` runs inline in this process; otherwise a spawn pool of ``min(workers, len(tasks))``
    processes, each of which loads ``scenarios`` (specs: ``ttompc.scenarios.scenario_spec(name)``) and runs
    ``initializer(*initargs)`` once (e.g. to load a model once per worker). With ``pin_torch`` torch uses one
    thread, in the workers and, for the duration of the inline run, in this process; data generation, which never
    touches torch, turns it off.
    """
    tasks = list(tasks)
    if not tasks:
        return
    if workers <= 1:
        with single_torch_thread() if pin_torch else contextlib.nullcontext():
            _start_worker((), False, initializer, initargs)
            yield from map(fn, tasks)
        return
    init_args = (tuple(scenarios), pin_torch, initializer, initargs)
    n = min(workers, len(tasks))
    with single_threaded_env(), mp.get_context("spawn").Pool(n, _start_pool_worker, init_args) as pool:
        yield from pool.imap(fn, tasks, chunksize=1)
