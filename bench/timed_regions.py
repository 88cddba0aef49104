"""Nested timed regions for the bench's profiles (``bench/step_profile.py``, ``bench/engine_limit.py``): a ``Profiler``
wraps functions as timed regions, named by the path of the regions they run in."""

from __future__ import annotations

import functools
import time
from collections import Counter, defaultdict
from collections.abc import Callable
from typing import Any

import torch


class Profiler:
    """Nested regions timed by ``clock`` (``time.perf_counter``: wall; ``time.process_time``: this process's CPU,
    steadier on a loaded machine): inclusive seconds and calls per path of region names (``step/scp/...``), plus
    counters. Off unless ``on``: warm-up and verification runs pass through untimed."""

    def __init__(self, cuda: bool = False, clock: Callable[[], float] = time.perf_counter) -> None:
        self.cuda, self.on, self.clock = cuda, False, clock
        self.reset()

    def reset(self) -> None:
        self.stack: list[str] = []
        self.incl: defaultdict[str, float] = defaultdict(float)
        self.calls: Counter[str] = Counter()
        self.count: defaultdict[str, float] = defaultdict(float)  # iterations, reused steps, backend-reported time
        self.iterations: Counter[int] = Counter()  # window subproblems per step (histogram over steps)

    def region(
        self, name: str, fn: Callable[..., Any], after: Callable[[Any, str], None] | None = None, sync: bool = False
    ) -> Callable[..., Any]:
        """``fn`` timed as region ``name``; ``after(result, path)`` records what the result says."""

        @functools.wraps(fn)
        def timed(*args: Any, **kwargs: Any) -> Any:
            if not self.on:
                return fn(*args, **kwargs)
            self.stack.append(name)
            path = "/".join(self.stack)
            t0 = self.clock()
            try:
                out = fn(*args, **kwargs)
                if sync and self.cuda:
                    torch.cuda.synchronize()
            finally:
                self.incl[path] += self.clock() - t0
                self.calls[path] += 1
                self.stack.pop()
            if after is not None:
                after(out, path)
            return out

        return timed

    def self_times(self) -> dict[str, float]:
        """Per path, its inclusive time less its direct children's."""
        out = dict(self.incl)
        for path, t in self.incl.items():
            parent = path.rpartition("/")[0]
            if parent:
                out[parent] = out.get(parent, 0.0) - t
        return out
