"""The one process pool of ttompc (data generation, DAgger collection, evaluation) and its thread pinning.

``pool_map`` runs tasks inline for one worker and otherwise in a *spawn* pool: fresh interpreters inherit no RNG,
torch or solver state, so results depend only on the task (with ``ttompc.seeding``) and not on the worker count.
Each worker gets one BLAS/OpenMP thread (``single_threaded_env``) and one torch thread: a pool of one worker per
core then does not oversubscribe the machine, and batch-1 model rollouts, chains of tiny kernels, run fastest on one
thread (measured in docs/design.md).

A worker that fails while starting (an unknown model in the initializer, a script without
``if __name__ == "__main__":`` that re-runs the command when a worker imports it) or dies later ends the whole
``pool_map`` with a ``WorkerError`` (one line through the CLI): ``concurrent.futures`` marks the pool broken instead
of starting replacement workers that fail the same way forever, as ``multiprocessing.Pool`` does.

What an initializer loads once per worker for its tasks (a scenario, a model) lives in a ``WorkerState``.
"""

from __future__ import annotations

import collections
import contextlib
import itertools
import multiprocessing as mp
import os
import signal
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Generic, TypeVar

from ttompc.errors import UserError

T = TypeVar("T")

_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
_STARTING = "TTOMPC_POOL_WORKER_STARTING"  # set for spawned workers until they have started (``starting_worker``)
_GRACE_S = 5.0  # seconds a terminated worker has to exit before it is killed
_AHEAD = 8  # tasks submitted per worker ahead of the one awaited: a slow task does not leave the others idle


class WorkerError(UserError):
    """A pool worker failed while starting, or died: the command stops instead of waiting forever."""


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


def starting_worker() -> bool:
    """True in a pool worker that has not finished starting, e.g. while it imports the parent's main script: a script
    that calls ``ttompc.cli.main()`` without ``if __name__ == "__main__":`` would run the command again there."""
    return _STARTING in os.environ


_start_failure: list[Exception] = []  # in a worker whose start failed: the error, which each of its tasks raises


def _start_pool_worker(*args: Any) -> None:
    """Ctrl-C reaches every process of the terminal's group: only the parent handles it (it stops the pool and
    says how to resume), so workers ignore it instead of each printing a traceback. A failed start is kept for
    ``_run_task`` to raise: the parent then stops with that error (an exception escaping here would only mark the
    pool broken, after a traceback, without saying why)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):  # born with it blocked (``_born_deaf``); ignored from here on
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    os.environ.pop(_STARTING, None)
    try:
        _start_worker(*args)
    except Exception as err:
        _start_failure.append(err)


@contextlib.contextmanager
def _born_deaf() -> Iterator[None]:
    """SIGINT blocked in this thread for the block, in which the pool spawns its workers: they inherit the mask, so
    a Ctrl-C that reaches a worker before ``_start_pool_worker`` ignores it stays pending and is then dropped,
    instead of raising ``KeyboardInterrupt`` in the worker's imports (a traceback on the terminal). Here a Ctrl-C
    that arrives in the block is delivered when it ends."""
    if not hasattr(signal, "pthread_sigmask"):  # Windows: no signal masks
        yield
        return
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def _run_task(fn: Callable[[Any], Any], task: Any) -> Any:
    if _start_failure:
        err = _start_failure[0]
        if isinstance(err, UserError):  # e.g. an unknown model: the same line as without a pool
            raise WorkerError(" ".join(str(err).split())) from err
        reason = " ".join(f"{type(err).__name__}: {err}".split())
        raise WorkerError(f"a worker process failed while starting ({reason})", "--debug shows where") from err
    return fn(task)


class WorkerState(Generic[T]):
    """What a ``pool_map`` initializer builds once per worker (a scenario, a loaded model, the config) for that
    worker's tasks: the initializer ``set``s it, each task ``get``s it. Create one at module level, next to the
    initializer and the task function. Every process holds its own value: each spawned worker, and this process when
    ``pool_map`` runs inline (``workers <= 1``), where a later run's initializer replaces the value."""

    def __init__(self) -> None:
        self._value: list[T] = []  # empty until ``set``

    def set(self, value: T) -> None:
        self._value[:] = [value]

    def get(self) -> T:
        """The value of the last ``set`` in this process; ``RuntimeError`` if there was none (a task called
        without the initializer ``pool_map`` runs first)."""
        if not self._value:
            raise RuntimeError("no worker state in this process: run the task through pool_map with its initializer")
        return self._value[0]


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
    with single_threaded_env():
        yield from _pool_results(fn, tasks, min(workers, len(tasks)), init_args)


def _pool_results(fn: Callable[[Any], Any], tasks: list[Any], n: int, init_args: tuple[Any, ...]) -> Iterator[Any]:
    """``pool_map``'s spawn pool: results in task order, at most ``_AHEAD`` tasks per worker submitted ahead. Any
    way out but the last result (an error, Ctrl-C, a consumer that stops) terminates the workers at once."""
    pool = ProcessPoolExecutor(n, mp.get_context("spawn"), initializer=_start_pool_worker, initargs=init_args)
    # All n workers start at the first submit, before the executor's thread: a spawn pool otherwise adds a worker per
    # submit while that thread may already walk its worker dict after a death (CPython 3.11: "dictionary changed
    # size during iteration", a traceback from that thread beside our one line).
    pool._safe_to_dynamically_spawn_children = False  # type: ignore[attr-defined]
    todo = iter(tasks)
    pending: collections.deque[Future[Any]] = collections.deque()
    finished = False
    os.environ[_STARTING] = "1"  # inherited by the workers, which clear it once started
    try:
        while True:
            with _born_deaf():  # submit() spawns the workers
                pending.extend(pool.submit(_run_task, fn, t) for t in itertools.islice(todo, n * _AHEAD - len(pending)))
            if not pending:
                break
            yield pending.popleft().result()
        finished = True
    except BrokenProcessPool as err:
        raise WorkerError(
            "a worker process exited unexpectedly: killed (e.g. out of memory), or it ran a script that calls "
            'ttompc.cli.main() without `if __name__ == "__main__":`',
            "guard that call, or use fewer workers",
        ) from err
    finally:
        os.environ.pop(_STARTING, None)
        if finished:
            pool.shutdown()
        else:
            _stop_now(pool)


def _stop_now(pool: ProcessPoolExecutor) -> None:
    """End ``pool`` without waiting for its running tasks, with bounded waits only: terminate each worker (kill one
    that is still alive after ``_GRACE_S``), reap it, then shut down without joining the executor's thread, which
    sees its workers gone and exits. ``shutdown()`` itself would wait for the running tasks (a DAgger chunk: minutes)
    and ProcessPoolExecutor has no terminate before Python 3.14."""
    processes = list((pool._processes or {}).values())
    for process in processes:
        process.terminate()
    for process in processes:
        process.join(_GRACE_S)
        if process.is_alive():
            process.kill()
            process.join(_GRACE_S)
    pool.shutdown(wait=False, cancel_futures=True)
