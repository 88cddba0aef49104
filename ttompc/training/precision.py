"""Training precision that fits the machine: ``trainer.precision: auto`` trains in bf16 autocast where the training
device computes bf16 natively and in fp32 elsewhere, where bf16 is emulated and several times slower (60 steps of
``recipes/generic/pretrain.yaml`` on an AVX2-only CPU: 85 s in ``bf16-mixed``, 14 s in ``32-true``).

``build_trainer`` resolves the recipe's value with ``resolve_precision`` and adds ``RecordPrecision``, which writes
the precision that ran into every checkpoint (``checkpoint["precision"]``; ``Planner.extra["precision"]`` of the
planners loaded from it).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import lightning as L

from ttompc.training.config import LightningPrecision, Precision

# /proc/cpuinfo flags of x86 CPUs whose vector or matrix units compute bf16 (AVX512-BF16, AMX-BF16)
NATIVE_BF16_FLAGS = frozenset({"avx512_bf16", "amx_bf16"})
CPUINFO = Path("/proc/cpuinfo")
# accelerators with which Lightning trains on a CUDA GPU when one is visible
_CUDA_ACCELERATORS = ("auto", "gpu", "cuda")


def read_cpu_flags(cpuinfo: Path = CPUINFO) -> frozenset[str]:
    """The CPU feature flags of ``cpuinfo``'s ``flags`` lines (Linux x86); empty when the file does not read."""
    try:
        text = cpuinfo.read_text(errors="ignore")
    except OSError:
        return frozenset()
    flags: set[str] = set()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "flags":
            flags.update(value.split())
    return frozenset(flags)


def resolve_precision(
    requested: Precision,
    *,
    accelerator: str = "auto",
    strategy: str = "auto",
    cuda: bool | None = None,
    cuda_bf16: bool | None = None,
    cpu_flags: Iterable[str] | None = None,
) -> LightningPrecision:
    """``requested`` unchanged unless it is ``auto``; ``auto`` is ``bf16-mixed`` where the training device computes
    bf16 natively and ``32-true`` elsewhere.

    The training device is Lightning's choice for ``accelerator``: a CUDA GPU for auto/gpu/cuda when one is visible
    (``cuda``; None: ask torch), bf16 when it has compute capability 8.0 or newer (``cuda_bf16``; None: ask torch,
    except under a fork-based ``strategy``, where asking would initialise CUDA before the fork: there fp32); else the
    CPU, bf16 when ``cpu_flags`` (None: ``/proc/cpuinfo``'s) hold AVX512-BF16 or AMX-BF16. Other accelerators (mps,
    tpu) resolve to fp32: set ``trainer.precision`` explicitly there."""
    if requested != "auto":
        return requested
    accelerator = accelerator.lower()
    if accelerator in _CUDA_ACCELERATORS:
        import torch

        if cuda is None:
            cuda = torch.cuda.is_available()  # NVML-based under Lightning: does not initialise CUDA
        if cuda:
            if cuda_bf16 is None:
                fork = "fork" in strategy or "notebook" in strategy
                cuda_bf16 = not fork and torch.cuda.is_bf16_supported(including_emulation=False)
            return "bf16-mixed" if cuda_bf16 else "32-true"
    elif accelerator != "cpu":
        return "32-true"
    flags = read_cpu_flags() if cpu_flags is None else frozenset(cpu_flags)
    return "bf16-mixed" if flags & NATIVE_BF16_FLAGS else "32-true"


class RecordPrecision(L.Callback):
    """Writes the Trainer's precision (what ran, resolved) into every full checkpoint as ``checkpoint["precision"]``."""

    def on_save_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict[str, Any]) -> None:
        checkpoint["precision"] = str(trainer.precision)
