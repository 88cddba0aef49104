"""Output folders are claimed, never overwritten: a command writes only into a folder that does not exist yet, is
empty, or holds its own earlier output (which it then resumes or refuses by its own fingerprint check); a folder
holding anything else — a user's files, another command's output — is refused before any work, in one line saying
what is there. A claimed folder is also one this process can write in (``writable``), found by trying."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

from ttompc.errors import UserError


def claim_folder(path: str | Path, command: str, own: Callable[[Path], bool]) -> None:
    """Refuse ``path`` as the output folder of ``ttompc command`` unless it is missing, empty, or ``own(folder)``
    (the folder holds the file only that command writes, e.g. a dataset's ``meta/generation.json``), and unless it
    can be created or written in (``writable``). Raises ``UserError`` naming up to four of the entries found, or the
    place that cannot be written; creates nothing."""
    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        raise UserError(f"cannot use {folder} (not a directory)", "choose a new or empty folder")
    entries = sorted(p.name for p in folder.iterdir()) if folder.is_dir() else []
    if entries and not own(folder):
        shown = ", ".join(entries[:4]) + (f" and {len(entries) - 4} more" if len(entries) > 4 else "")
        raise UserError(
            f"{folder} holds files that `ttompc {command}` did not write ({shown})",
            "choose a new or empty folder; nothing was changed",
        )
    writable(folder)


def writable(path: str | Path) -> None:
    """The folder ``path`` can be created or written into: its nearest existing ancestor is a folder this process
    can write in, found by trying (a file created there and removed at once: permission bits do not tell for root,
    a read-only file system or a kernel file system), so that an output a command may not write is refused (one
    line, worded as the CLI's error for such a path) before the work, not after it. Leaves nothing behind."""
    target = Path(path).absolute()
    existing = next(p for p in (target, *target.parents) if p.exists())
    reason = "not a directory" if not existing.is_dir() else None
    if reason is None:
        try:
            handle, probe = tempfile.mkstemp(prefix=".ttompc-write-test-", dir=existing)
        except OSError as err:
            reason = (err.strerror or type(err).__name__).lower()
        else:
            os.close(handle)
            os.unlink(probe)
    if reason is not None:
        raise UserError(
            f"cannot use {existing} ({reason})", "choose a location you can write to, or fix its permissions"
        )
