"""The machine a measurement ran on, as reports and benchmarks record it beside their timings: the CPU's model, its
cores and the load averages (step times on a loaded machine are longer, and say so)."""

from __future__ import annotations

import os
import platform
from pathlib import Path
from typing import Any


def load_average() -> list[float]:
    """The 1-, 5- and 15-minute load averages now, to two decimals."""
    return [round(x, 2) for x in os.getloadavg()]


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo), else the machine type."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_record(load_start: list[float]) -> dict[str, Any]:
    """A report's ``machine``: ``cpu`` (model), ``cpus`` (cores), ``load_average`` (1/5/15 minutes) at the start
    (``load_start``, from ``load_average``) and at the end (now, ``load_average_end``)."""
    return {"cpu": cpu_model(), "cpus": os.cpu_count(), "load_average": load_start, "load_average_end": load_average()}


def machine_label(machine: dict[str, Any] | None) -> str:
    """'CPU, N cores, load L' (the larger of the 15-minute load averages at the start and the end) for a figure, or
    'machine not recorded'."""
    if not machine:
        return "machine not recorded"
    load = max(machine["load_average"][2], machine["load_average_end"][2])
    return f"{machine['cpu']}, {machine['cpus']} cores, load {load:.1f}"
