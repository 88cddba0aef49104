"""Compiled code: numba's ``njit`` and ``cfunc`` with numba's on-disk cache keyed on the content of all of a kernel's
source files, and the fallbacks where that cache is not available. Imports neither torch nor Lightning, and numba
only when a kernel first compiles a function.

numba keys a cached function on its own file (its modification time and size), while a compiled function contains
the functions it calls from other files: after an edit to one of those, the cached callers would still run the old
code. A ``Kernel`` therefore stamps every function it compiles with one hash of all of its ``sources``: editing any
of them recompiles the whole kernel once, and a checkout that only changes the files' times recompiles nothing.

The stamp is written into a private attribute of numba's cache (the source stamp of its index file), this package's
one use of numba's internals. ``cache_support`` checks once per process, on a probe function and before any kernel
compiles, that numba can cache here and still has that attribute. Where it has not, a kernel of several files
compiles in every process instead (correct, ~10-20 s per process) and a one-file kernel keeps numba's own key (its
file: also correct), each with one ``RuntimeWarning`` naming the numba version; where no cache folder is writable
(``NUMBA_CACHE_DIR``, the source's ``__pycache__``, the user's cache folder), every kernel compiles in every process,
with a warning saying how to fix it.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal

NO_LOCATOR = "no locator available"  # numba's RuntimeError where no cache folder is writable

CacheMode = Literal["stamp", "numba", "none"]


def _probe() -> int:  # pragma: no cover - never called, only decorated
    return 0


def _index_file(compiled: Any) -> Any:
    """numba's cache index of a dispatcher or cfunc (None where it has none)."""
    return getattr(getattr(compiled, "_cache", None), "_cache_file", None)


@functools.cache
def cache_support() -> tuple[bool, bool]:
    """(numba can cache compiled code on disk here, its cache index has the source stamp a ``Kernel`` sets),
    checked once per process on a probe function of this module (decorating it compiles nothing)."""
    from numba import njit

    try:
        probe = njit(cache=True)(_probe)
    except RuntimeError as err:
        if NO_LOCATOR not in str(err):
            raise
        return False, False
    return True, hasattr(_index_file(probe), "_source_stamp")


def cache_mode(cacheable: bool, stampable: bool, own_file: bool) -> tuple[CacheMode, str | None]:
    """How a kernel caches (``stamp``: keyed on all its sources, ``numba``: numba's key, its own file, ``none``: no
    disk cache) and the warning to show, if any, given ``cache_support()`` and whether the kernel's sources are just
    the compiled function's own file."""
    if not cacheable:
        return "none", "cannot be cached (no writable numba cache folder): set NUMBA_CACHE_DIR to a writable folder"
    if stampable:
        return "stamp", None
    if own_file:
        return "numba", None
    import numba

    return "none", (
        f"is compiled in every process: numba {numba.__version__}'s cache has no source stamp to key it on all of "
        "its files (ttompc.compiled)"
    )


class Kernel:
    """Compiles the functions of one kernel: ``label`` names it in warnings, ``sources`` are the files whose content
    keys its disk cache (every file holding code compiled into it), ``options`` go to every ``njit``."""

    def __init__(self, label: str, sources: Sequence[Path], **options: Any) -> None:
        self.label, self.sources, self.options = label, tuple(Path(s) for s in sources), options

    @functools.cached_property
    def stamp(self) -> str:
        """The hash of the kernel's source files (names and content, read once per process)."""
        digest = hashlib.sha256()
        for path in self.sources:
            digest.update(path.name.encode())
            digest.update(path.read_bytes())
        return digest.hexdigest()

    def jit(self, func: Callable, *, forceinline: bool = False) -> Any:  # a numba dispatcher
        """``func`` as an ``njit`` dispatcher with the kernel's options (``forceinline``: LLVM inlines it into its
        callers), cached on disk as the module docstring says."""
        from numba import njit

        return self._compile(func, lambda cache: njit(cache=cache, forceinline=forceinline, **self.options)(func))

    def cfunc(self, func: Callable, signature: Any) -> Any:  # a numba CFunc
        """``func`` as a numba ``cfunc`` of ``signature`` (a C function, called by address from other compiled
        code), cached on disk as the module docstring says."""
        from numba import cfunc

        return self._compile(func, lambda cache: cfunc(signature, cache=cache, **self.options)(func))

    def _compile(self, func: Callable, make: Callable[[bool], Any]) -> Any:
        own_file = self.sources == (Path(inspect.getfile(func)),)
        mode, problem = cache_mode(*cache_support(), own_file)
        if mode != "none":
            try:
                compiled = make(True)
            except RuntimeError as err:  # this source's folder has no writable cache where the probe's had one
                if NO_LOCATOR not in str(err):
                    raise
                mode, problem = cache_mode(False, False, own_file)
        if mode == "none":
            compiled = make(False)
        elif mode == "stamp":
            _index_file(compiled)._source_stamp = self.stamp
        if problem is not None:
            warnings.warn(f"{self.label} {problem}", RuntimeWarning, stacklevel=1)  # once per kernel
        return compiled


def own_file_kernel(label: str, func: Callable, **options: Any) -> Kernel:
    """The ``Kernel`` of one function that calls no compiled code from other files, keyed on its own file."""
    return Kernel(label, [Path(inspect.getfile(func))], **options)
