"""Run many ``ttompc`` command lines through the real CLI entry point (``ttompc.cli.main``) in one subprocess, so a
table of bad inputs costs one interpreter start per batch, not per case; and a folder that refuses this process.

``python tests/cli_batch.py CASES.json RESULTS.json``: CASES is a list of ``{"id", "argv", "env"}`` run in order in
the current folder; RESULTS maps each id to its exit code, stderr, whether an exception escaped ``main`` (a
traceback: ``traceback``) and the files of the current folder that the case created, changed or removed
(``changed``; content and mode compared before and after).
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import signal
import sys
import traceback
from pathlib import Path


def snapshot(root: Path) -> dict[str, str]:
    """Path -> digest of content and mode, for every file and folder under ``root``."""
    out = {}
    for path in sorted(root.rglob("*")):
        stat = path.lstat()
        data = path.read_bytes() if path.is_file() and stat.st_mode & 0o400 else b""
        out[str(path.relative_to(root))] = hashlib.sha256(data + oct(stat.st_mode).encode()).hexdigest()
    return out


class Overrun(Exception):
    """A case that ran longer than ``LIMIT_S``: it started work a bad input should have stopped."""


LIMIT_S = 60


def _overrun(signum: int, frame: object) -> None:
    raise Overrun(f"still running after {LIMIT_S} s")


def run_case(argv: list[str], env: dict[str, str]) -> dict[str, object]:
    """One command line through ``ttompc.cli.main``; a case that overruns ``LIMIT_S`` counts as a traceback."""
    from ttompc.cli import main

    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    err, out = io.StringIO(), io.StringIO()
    escaped = None
    signal.signal(signal.SIGALRM, _overrun)
    signal.alarm(LIMIT_S)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            try:
                code = main(argv)
            except SystemExit as exit_:  # argparse's errors
                code = exit_.code if isinstance(exit_.code, int) else 1
    except BaseException:  # what a user would see as a traceback
        code, escaped = 1, traceback.format_exc()
    finally:
        signal.alarm(0)
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
    return {"code": code, "stderr": err.getvalue(), "stdout": out.getvalue(), "traceback": escaped}


def can_write(folder: Path) -> bool:
    try:
        (folder / ".probe").touch()
    except OSError:
        return False
    (folder / ".probe").unlink()
    return True


def read_only_folder(root: Path) -> Path | None:
    """A folder this process cannot write in: a mode-555 folder under ``root``, or where that does not stop it
    (root, as CI and these machines run the suite) a folder of a kernel file system: sysfs and procfs let no one
    create a file, root included, even mounted read-write, so on Linux there is always one; None when there is
    none (another system, run as root)."""
    folder = root / "read-only"
    folder.mkdir(exist_ok=True)
    folder.chmod(0o555)
    if not can_write(folder):
        return folder
    folder.chmod(0o755)
    folder.rmdir()
    kernel = (Path("/sys/kernel"), Path("/sys"), Path("/proc/sys"), Path("/proc"))
    return next((p for p in kernel if p.is_dir() and not can_write(p)), None)


def main() -> None:
    cases = json.loads(Path(sys.argv[1]).read_text())
    root = Path.cwd()
    results = {}
    for case in cases:
        before = snapshot(root)
        result = run_case(case["argv"], case.get("env", {}))
        after = snapshot(root)
        result["changed"] = sorted(k for k in before.keys() | after.keys() if before.get(k) != after.get(k))
        results[case["id"]] = result
    Path(sys.argv[2]).write_text(json.dumps(results))


if __name__ == "__main__":
    main()
