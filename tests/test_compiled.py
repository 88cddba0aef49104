"""``ttompc.compiled``: a kernel's disk cache is keyed on all of its sources (an edit to a callee's file recompiles
its callers; an unchanged kernel loads from the cache), and the fallbacks where numba's cache cannot be keyed so."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from ttompc.compiled import Kernel, cache_mode

KERNEL = """
from pathlib import Path
from typing import Any
from ttompc.compiled import Kernel
HERE = Path(__file__).parent
K = Kernel("the test kernel", [HERE / "kern.py", HERE / "callee.py", HERE / "caller.py"])
"""
CALLEE = """
from kern import K

@K.jit
def g(x):
    return x + {value}
"""
CALLER = """
from kern import K
from callee import g

@K.jit
def f(x):
    return 2 * g(x)
"""
RUN = "import caller; print(caller.f(1), sum(caller.f.stats.cache_hits.values()))"


def _run(folder: Path) -> tuple[int, int]:
    """f(1) and the number of cache hits in a fresh process (the cache in ``folder``/cache)."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(folder / "cache"), "PYTHONPATH": str(folder)}
    out = subprocess.run([sys.executable, "-c", RUN], cwd=folder, env=env, capture_output=True, text=True, check=True)
    value, hits = out.stdout.split()
    return int(value), int(hits)


def test_an_edit_to_any_source_recompiles_the_kernel(tmp_path: Path) -> None:
    (tmp_path / "kern.py").write_text(KERNEL)
    (tmp_path / "caller.py").write_text(CALLER)
    (tmp_path / "callee.py").write_text(CALLEE.format(value=1))
    assert _run(tmp_path) == (4, 0)  # compiled
    assert _run(tmp_path) == (4, 1)  # loaded from the disk cache
    # the caller's file is untouched: numba's own key (its file) would load f with the old g inlined, giving 4
    (tmp_path / "callee.py").write_text(CALLEE.format(value=5))
    assert _run(tmp_path) == (12, 0)
    assert _run(tmp_path) == (12, 1)


def test_the_stamp_follows_content_not_file_times(tmp_path: Path) -> None:
    a, b = tmp_path / "a.py", tmp_path / "b.py"
    a.write_text("x = 1\n")
    b.write_text("y = 2\n")
    stamp = Kernel("k", [a, b]).stamp
    os.utime(b, (0, 0))
    assert Kernel("k", [a, b]).stamp == stamp
    b.write_text("y = 3\n")
    assert Kernel("k", [a, b]).stamp != stamp


@pytest.mark.parametrize(
    ("cacheable", "stampable", "own_file", "mode", "warns"),
    [
        (True, True, False, "stamp", False),
        (True, True, True, "stamp", False),
        (True, False, True, "numba", False),  # numba's own key is right for a one-file kernel
        (True, False, False, "none", True),  # it would load stale callers: compile in every process, say so
        (False, False, True, "none", True),  # no writable cache folder
        (False, False, False, "none", True),
    ],
)
def test_the_fallbacks(cacheable: bool, stampable: bool, own_file: bool, mode: str, warns: bool) -> None:
    got, warning = cache_mode(cacheable, stampable, own_file)
    assert got == mode and (warning is not None) == warns


def test_a_kernel_compiles_where_its_stamp_cannot_be_set(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """With numba's cache lacking the stamp, a kernel of several files still compiles and runs, warning once."""
    import ttompc.compiled as compiled

    monkeypatch.setattr(compiled, "cache_support", lambda: (True, False))
    kernel = Kernel("the fallback test kernel", [Path(__file__), tmp_path / "other.py"])

    def twice(x: int) -> int:
        return 2 * x

    with pytest.warns(RuntimeWarning, match="compiled in every process"):
        assert kernel.jit(twice)(21) == 42
