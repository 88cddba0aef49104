"""The numba form of a scenario's approximate dynamics (``BatchedModel.fused_step``), for the fused decode
(``ttompc.policy.fused``): one C signature for every scenario's step, so one compiled decode kernel calls any of them
by address. numba is imported on first use (the scenarios do not need it otherwise)."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

from ttompc.compiled import own_file_kernel


def fused_step_signature() -> Any:
    """The numba signature of a ``BatchedModel.fused_step`` step: void(float32* s, float32* a, intp k, float32* p,
    float32* out)."""
    from numba import types

    f32 = types.CPointer(types.float32)
    return types.void(f32, f32, types.intp, f32, f32)


@functools.cache
def compile_fused_step(func: Callable[..., None]) -> Any:
    """``func`` (a module-level function indexing its pointer arguments, ``BatchedModel.fused_step``) as a numba
    cfunc of ``fused_step_signature()``, compiled once per process at most and cached on disk keyed on ``func``'s
    file (``ttompc.compiled``: it may call no compiled code from other files)."""
    kernel = own_file_kernel(f"the fused step {func.__module__}.{func.__qualname__}", func)
    return kernel.cfunc(func, fused_step_signature())
