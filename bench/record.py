"""What every bench script records beside its figures (docs/benchmarks.md): the machine and its load over the run,
and the result file with its one printed JSON line.

A script runs as ``python bench/NAME.py``, which puts bench/ first on ``sys.path``, so it imports this module as
``from record import Machine, result_path, write_result``: ``machine = Machine()`` when the measuring starts,
``machine.record()`` merged into the result when it ends, then ``write_result(result, out)``.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ttompc.evaluation.machine import cpu_model, load_average
from ttompc.evaluation.metrics import write_json

__all__ = ["Machine", "load_average", "read_result", "result_path", "write_result"]

RESULTS = Path(__file__).resolve().parent / "results"


def result_path(name: str) -> Path:
    """``bench/results/NAME.json``: where a script writes its result unless told otherwise (``--out``)."""
    return RESULTS / f"{name}.json"


def git_commit() -> str | None:
    """HEAD of the checkout, with ``+dirty`` when the working tree has changes (what the numbers were run on); None
    outside a git checkout."""
    root = RESULTS.parent.parent
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True)
        dirty = subprocess.run(["git", "status", "--porcelain"], cwd=root, capture_output=True, text=True, check=True)
    except (OSError, subprocess.CalledProcessError):
        return None
    return head.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")


class Machine:
    """The machine a run measures on, from construction (the start of the measuring: its load average and clock)
    to ``record`` (its end)."""

    def __init__(self) -> None:
        self.load_start = load_average()
        self.started = time.perf_counter()

    def record(self) -> dict[str, Any]:
        """The run's machine record, one set of keys for every script: ``host``, ``platform``, ``cpu`` (model
        name), ``cpus``, ``python``, ``torch`` and ``torch_threads`` (the version and intra-op threads of the torch
        the run imported; None without torch), ``omp_num_threads`` (the environment's, None when unset), ``commit``
        (``git_commit``), ``date`` (UTC, now), ``load_average`` (1/5/15 minutes, at the start), ``load_average_end``
        (now) and ``wall_s`` (seconds since the start)."""
        torch = sys.modules.get("torch")
        return {
            "host": platform.node(),
            "platform": platform.platform(),
            "cpu": cpu_model(),
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "torch": None if torch is None else torch.__version__,
            "torch_threads": None if torch is None else torch.get_num_threads(),
            "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
            "commit": git_commit(),
            "date": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
            "load_average": self.load_start,
            "load_average_end": load_average(),
            "wall_s": time.perf_counter() - self.started,
        }


def read_result(path: str | Path) -> dict[str, Any]:
    """The result a previous run wrote to ``path`` ({} when there is none): what a script that re-runs one part
    (``--only``) keeps of the others."""
    path = Path(path)
    return json.loads(path.read_text()) if path.is_file() else {}


def write_result(result: Mapping[str, Any], out: str | Path | None, line: Mapping[str, Any] | None = None) -> None:
    """Write ``result`` to ``out`` (strict JSON, indented: numpy values converted, non-finite floats as null; its
    folder made) unless ``out`` is None (a smoke run writes nothing), then print ``line`` (default: the whole
    result) as one JSON line."""
    if out is not None:
        write_json(out, result)
    print(json.dumps(result if line is None else line, default=lambda x: x.tolist()))
