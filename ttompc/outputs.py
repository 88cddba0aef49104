"""Output folders are claimed, never overwritten: a command writes only into a folder that does not exist yet, is
empty, or holds its own earlier output (which it then resumes or refuses by its own fingerprint check); a folder
holding anything else — a user's files, another command's output — is refused before any work, in one line saying
what is there."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from ttompc.errors import UserError


def claim_folder(path: str | Path, command: str, own: Callable[[Path], bool]) -> None:
    """Refuse ``path`` as the output folder of ``ttompc command`` unless it is missing, empty, or ``own(folder)``
    (the folder holds the file only that command writes, e.g. a dataset's ``meta/generation.json``). Raises
    ``UserError`` naming up to four of the entries found; creates nothing."""
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
