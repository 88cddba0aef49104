"""``jit`` and ``jit_inlined``, the decorators of the Riccati kernel's compiled functions: one
``ttompc.compiled.Kernel`` whose disk cache is keyed on the content of all of ``KERNEL_SOURCES`` (a compiled function
contains the functions it calls from the other files, and this file holds the compile options), so editing any of
them recompiles the whole kernel once. No fastmath: it drops the NaN checks a breakdown needs.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from ttompc.compiled import Kernel

KERNEL_SOURCES = ("riccati_jit.py", "riccati_rows.py", "riccati_cone.py", "riccati_kernel.py")  # in this folder
KERNEL = Kernel(
    "the riccati backend's kernel", [Path(__file__).parent / name for name in KERNEL_SOURCES], error_model="numpy"
)


def jit(func: Callable) -> Any:  # a numba dispatcher
    """A function of the kernel, compiled (once per machine and edit of ``KERNEL_SOURCES``, ~10-20 s in all)."""
    return KERNEL.jit(func)


def jit_inlined(func: Callable) -> Any:  # a numba dispatcher
    """``jit`` for a part of ``riccati_kernel._ipm``, inlined into it by LLVM (``forceinline``): the part's arrays are
    then ``_ipm``'s, with no call to pass them through and what LLVM knows of them (they do not overlap) kept; as
    separate functions the parts cost 5-15% more (measured against the single-function kernel they were split from).

    A part stays a leaf with one way out (no early return, no call that is not inlined): numba counts a reference to
    each array argument on entry, and only there does it prune the counts before inlining, where they would cost as
    much again. Nor does a part slice arrays: numba compiles the library code it calls (the slice's error message)
    inlined as well, which multiplies the compiled code and its compile time."""
    return KERNEL.jit(func, forceinline=True)
