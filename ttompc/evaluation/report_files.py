"""Report files of ``ttompc evaluate``: written whole or not at all, and read only when complete.

A report's JSON (``mpc.json``, ``warmstart.json``) is removed before its command writes the report's other files
(``retract``) and written last, after its table, CSVs and plots, in one atomic rename (``metrics.write_json``),
recording ``"complete": true`` (``finish``). A folder
whose JSON is missing or lacks that mark holds an interrupted run (or one of a ttompc before the mark), whatever
other files it holds: ``read_report`` refuses it, and it is how every consumer of a report opens one
(``ttompc evaluate compare``, ``make figures``, ``ttompc zoo metrics``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ttompc.errors import UserError
from ttompc.evaluation.metrics import write_json

COMPLETE = "complete"


def retract(path: Path) -> None:
    """Remove the report's JSON at ``path`` before its other files are written again: until ``finish`` writes the new
    one, the folder holds no complete report (an earlier report's JSON never vouches for new tables and CSVs)."""
    path.unlink(missing_ok=True)


def finish(path: Path, report: dict[str, Any]) -> Path:
    """Write ``report`` to ``path`` marked complete: call it after every other file of the report is written."""
    return write_json(path, {**report, COMPLETE: True})


def read_report(path: str | Path, kind: str) -> dict[str, Any]:
    """The complete report of ``ttompc evaluate KIND`` at ``path`` (its JSON, nulls as written); raises
    ``UserError`` (one line, what to do) for a missing or unreadable file, or a report not marked complete."""
    path = Path(path)
    again = f"run `ttompc evaluate {kind} ...` (a closed-loop sweep resumes where it stopped)"
    if not path.is_file():
        raise UserError(f"no report at {path}", again)
    try:
        report = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as err:
        raise UserError(f"{path} is not a report's JSON ({err})", again) from err
    if not isinstance(report, dict) or report.get(COMPLETE) is not True:
        raise UserError(
            f"{path} is not a complete report (its run stopped before the end, or an older ttompc wrote it)", again
        )
    return report
