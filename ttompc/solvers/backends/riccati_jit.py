"""``jit``, the decorator of the Riccati kernel's compiled functions: numba's ``njit`` with its on-disk cache, keyed on
the content of all the kernel's source files.

numba keys a cached function on its own source file only, while a compiled function contains the functions it calls
from other files: after an edit to ``riccati_cone.py`` the cached ``riccati_kernel`` functions would still run the
old cone code. ``jit`` therefore stamps every function of the kernel with one hash of all of ``KERNEL_SOURCES``:
editing any of them recompiles the whole kernel once.
"""

from __future__ import annotations

import functools
import hashlib
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

from numba import njit

KERNEL_SOURCES = ("riccati_jit.py", "riccati_rows.py", "riccati_cone.py", "riccati_kernel.py")  # in this folder


@functools.cache
def kernel_stamp() -> str:
    """The hash of the kernel's source files (read once per process)."""
    digest = hashlib.sha256()
    for name in KERNEL_SOURCES:
        digest.update(name.encode())
        digest.update((Path(__file__).parent / name).read_bytes())
    return digest.hexdigest()


def jit(func: Callable, forceinline: bool = False) -> Any:  # a numba dispatcher
    """``njit`` with numba's on-disk cache under ``kernel_stamp`` (no fastmath: it drops the NaN checks a breakdown
    needs). Where no cache folder is writable (``NUMBA_CACHE_DIR``, the package's ``__pycache__``, the user's cache
    folder) numba refuses to decorate: the kernel then compiles in every process that uses it instead of failing to
    import, with a warning."""
    try:
        dispatcher = njit(cache=True, error_model="numpy", forceinline=forceinline)(func)
    except RuntimeError as err:
        if "no locator available" not in str(err):
            raise
        warnings.warn(
            "the riccati backend's kernel cannot be cached (no writable numba cache folder): it compiles in every "
            "process (~10-20 s); set NUMBA_CACHE_DIR to a writable folder to compile it once",
            RuntimeWarning,
            stacklevel=1,  # this line, not each decorated function's: shown once
        )
        return njit(error_model="numpy", forceinline=forceinline)(func)
    # numba's cache index compares this stamp (by default the hash of the function's own file) with the stored one
    cache_file = getattr(getattr(dispatcher, "_cache", None), "_cache_file", None)
    if cache_file is not None and hasattr(cache_file, "_source_stamp"):
        cache_file._source_stamp = kernel_stamp()
    else:
        warnings.warn(
            "numba's cache has changed its layout: the riccati kernel's cache is keyed on each function's own file, "
            f"so after an edit to one of {KERNEL_SOURCES} delete their numba cache (__pycache__/riccati_*.nb*)",
            RuntimeWarning,
            stacklevel=1,
        )
    return dispatcher


def jit_inlined(func: Callable) -> Any:  # a numba dispatcher
    """``jit`` for a part of ``riccati_kernel._ipm``, inlined into it by LLVM (``forceinline``): the part's arrays are
    then ``_ipm``'s, with no call to pass them through and what LLVM knows of them (they do not overlap) kept; as
    separate functions the parts cost 5-15% more (measured against the single-function kernel they were split from).

    A part stays a leaf with one way out (no early return, no call that is not inlined): numba counts a reference to
    each array argument on entry, and only there does it prune the counts before inlining, where they would cost as
    much again. Nor does a part slice arrays: numba compiles the library code it calls (the slice's error message)
    inlined as well, which multiplies the compiled code and its compile time."""
    return jit(func, forceinline=True)
