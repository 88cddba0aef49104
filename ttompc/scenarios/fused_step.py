"""The numba form of a scenario's approximate dynamics (``BatchedModel.fused_step``), for the fused decode
(``ttompc.policy.fused``): one C signature for every scenario's step, so one compiled decode kernel calls any of them
by address. numba is imported on first use (the scenarios do not need it otherwise)."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any


def fused_step_signature() -> Any:
    """The numba signature of a ``BatchedModel.fused_step`` step: void(float32* s, float32* a, intp k, float32* p,
    float32* out)."""
    from numba import types

    f32 = types.CPointer(types.float32)
    return types.void(f32, f32, types.intp, f32, f32)


@functools.cache
def compile_fused_step(func: Callable[..., None]) -> Any:
    """``func`` (a module-level function indexing its pointer arguments, ``BatchedModel.fused_step``) as a numba
    cfunc of ``fused_step_signature()``, cached on disk by numba (keyed on ``func``'s file), compiled once per
    process at most; where no cache folder is writable, compiled in every process."""
    from numba import cfunc

    try:
        return cfunc(fused_step_signature(), cache=True)(func)
    except RuntimeError as err:
        if "no locator available" not in str(err):
            raise
        return cfunc(fused_step_signature())(func)
