"""How every long command shows progress: on stderr, so that stdout carries only the command's result (JSON, a
table) and stays parseable.

* ``status(line)`` names a phase that starts and cannot be counted (importing Lightning, loading a model), so a
  command says something within seconds of its start;
* ``Bar`` counts work (problems, episodes, rollouts) with rate and ETA. It redraws its elapsed time every second, so
  an item that takes minutes (one closed-loop problem) still shows the command is alive, and ``Bar.ticker()``
  lets pool workers advance it from their processes at a finer grain than the pool's tasks;
* training's step bar (``ttompc.training.progress.StepProgressBar``) draws through Lightning, on stderr too.

On by default; ``TTOMPC_PROGRESS=0`` turns it off, and it is off when ``CI`` is set (CI logs do not redraw lines)
unless ``TTOMPC_PROGRESS=1``. Progress never stops a command: when stderr is closed or broken (``2>&1 | head``) it
is dropped (``STDERR``).
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import sys
import threading
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any, TypeVar

from tqdm import tqdm

T = TypeVar("T")
HEARTBEAT_S = 1.0  # how often a bar redraws its elapsed time when nothing finishes


class _Stderr:
    """``sys.stderr`` (looked up at each write, so captured streams work) that drops what it cannot write. tqdm
    draws while holding its global lock and does not release it when the write raises: a broken pipe in the
    heartbeat thread would leave the lock held and hang the next bar, or the command."""

    def write(self, text: str) -> int:
        try:
            return sys.stderr.write(text)
        except (OSError, ValueError):  # broken pipe, closed file
            return 0

    def flush(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            sys.stderr.flush()

    def __getattr__(self, name: str) -> Any:  # encoding, fileno, isatty: what tqdm asks of its file
        return getattr(sys.stderr, name)


STDERR: Any = _Stderr()  # where all progress goes


def progress_enabled() -> bool:
    """Whether progress is shown: ``TTOMPC_PROGRESS`` if set, else off under ``CI``."""
    setting = os.environ.get("TTOMPC_PROGRESS", "").strip().lower()
    if setting:
        return setting not in ("0", "false", "no", "off")
    return not os.environ.get("CI")


def status(line: str) -> None:
    """One line on stderr naming a phase that has started (nothing when progress is off)."""
    if progress_enabled():
        print(line, file=STDERR, flush=True)


@dataclass(frozen=True)
class Ticker:
    """Advances a ``Bar`` by one from any process. Pass it to pool workers in their initializer's arguments (it can
    be pickled while the pool starts its workers); a no-op when the bar is hidden."""

    queue: Any = None

    def __call__(self) -> None:
        if self.queue is not None:
            self.queue.put(1)


class Bar:
    """A progress bar on stderr for ``total`` units of work (None: unknown), used as a context manager. Hidden, and
    every method a no-op, when ``show`` is false or progress is off."""

    def __init__(
        self, total: float | None, desc: str, unit: str = "it", *, show: bool = True, initial: float = 0
    ) -> None:
        """``initial``: units already done before this bar started (a resumed run): counted, not in the rate."""
        self.enabled = show and progress_enabled()
        shown = {"desc": desc, "unit": unit, "file": STDERR, "dynamic_ncols": True, "initial": initial}
        self._bar = tqdm(total=total, disable=not self.enabled, **shown)
        self._lock = threading.Lock()  # tqdm's counters are not thread-safe: the heartbeat and ticks share them
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._queue: Any = None
        self._fraction = 0.0  # counted but not yet shown: less than one unit
        if self.enabled:
            self._start(self._heartbeat)

    def __enter__(self) -> Bar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def update(self, n: float = 1) -> None:
        """Count ``n`` more units; fractions (a share of a batch of episodes run in lockstep) add up until they make
        whole units, which the bar shows (it would print 0.6666666666666666/2)."""
        if self.enabled:
            with self._lock:
                self._fraction += n
                whole = int(self._fraction + 1e-9)  # 3 x 1/3 is one unit, not 0.9999999999999999
                if whole:
                    self._fraction -= whole
                    self._bar.update(whole)

    def set_postfix(self, **values: Any) -> None:
        if self.enabled:
            with self._lock:
                self._bar.set_postfix(values)

    def each(self, results: Iterable[T]) -> Iterator[T]:
        """``results`` (e.g. of a pool), each counted as it arrives: its work is done."""
        for result in results:
            self.update()
            yield result

    def ticker(self) -> Callable[[], None]:
        """A picklable callable that advances this bar by one from this or a worker process."""
        if not self.enabled:
            return Ticker()
        if self._queue is None:
            # a SimpleQueue writes before put() returns: a worker's ticks are in the pipe before its task's result
            self._queue = mp.get_context("spawn").SimpleQueue()
            self._start(self._listen)
        return Ticker(self._queue)

    def close(self) -> None:
        """Stop redrawing, count the ticks still queued, and leave the bar's last state on screen."""
        self._stop.set()
        for thread in self._threads:
            thread.join()
        self._threads.clear()
        self._drain()  # what the listener left (it stops at the first empty poll after the stop)
        self._bar.close()

    def _start(self, target: Callable[[], None]) -> None:
        thread = threading.Thread(target=target, name=f"ttompc-progress-{target.__name__}", daemon=True)
        thread.start()
        self._threads.append(thread)

    def _heartbeat(self) -> None:
        while not self._stop.wait(HEARTBEAT_S):
            with self._lock:
                self._bar.refresh()

    def _listen(self) -> None:
        while not self._stop.wait(0.05):
            self._drain()

    def _drain(self) -> None:
        """Count every tick queued so far (each ``put`` is in the pipe before it returns)."""
        while self._queue is not None and not self._queue.empty():
            self.update(self._queue.get())
