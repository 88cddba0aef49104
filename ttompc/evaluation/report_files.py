"""Report files of ``ttompc evaluate``: written whole or not at all, and read only when complete.

A report's JSON (``mpc.json``, ``warmstart.json``) is removed before its command writes the report's other files
(``retract``) and written last, after its table, CSVs and plots, in one atomic rename (``metrics.write_json``),
recording ``"complete": true`` (``finish``). A folder
whose JSON is missing or lacks that mark holds an interrupted run (or one of a ttompc before the mark), whatever
other files it holds: ``read_report`` refuses it, and it is how every consumer of a report opens one
(``ttompc evaluate compare``, ``make figures``, ``ttompc zoo metrics``).

A report that is computed whole (``warmstart``) is replaced by a run of the same configuration, and a complete report
of another configuration in the folder is refused before any work (``check_replaceable``), as a closed-loop sweep
refuses episodes of another configuration (``ttompc.evaluation.episode_store``, whose comparison
``config_differences`` is).

A report's folder is claimed before any work, by the library call as by the command (``claim_report``): it is new,
empty or a report folder of that kind, never a dataset or a user's folder.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ttompc.errors import UserError
from ttompc.evaluation.metrics import write_json
from ttompc.evaluation.reproduce import INERT
from ttompc.outputs import claim_folder

COMPLETE = "complete"


def claim_report(folder: str | Path, kind: str) -> Path:
    """``folder`` as the report folder of ``ttompc evaluate KIND``: refused (``UserError``, one line saying what is
    there) unless it is missing, empty or holds files named ``<kind>*`` (a report of this kind, which the run then
    resumes, replaces or refuses by its configuration), and unless this process can write there
    (``ttompc.outputs.claim_folder``). Creates nothing; returns ``folder`` as a ``Path``."""
    claim_folder(folder, f"evaluate {kind}", lambda there: any(p.name.startswith(kind) for p in there.iterdir()))
    return Path(folder)


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


def config_differences(a: dict[str, Any], b: dict[str, Any], prefix: str = "") -> list[str]:
    """'key: A here, B there' for every (nested) key whose value differs between ``a`` (this run's) and ``b``."""
    out = []
    for key in dict.fromkeys([*a, *b]):
        x, y = a.get(key), b.get(key)
        if isinstance(x, dict) and isinstance(y, dict):
            out += config_differences(x, y, f"{prefix}{key}.")
        elif x != y:
            out.append(f"{prefix}{key}: {json.dumps(x)} here, {json.dumps(y)} there")
    return out


def check_replaceable(path: Path, kind: str, config: dict[str, Any]) -> None:
    """``ttompc evaluate KIND`` with ``config`` may write its report over ``path``: there is none, or it is not
    complete (an interrupted run's, replaced), or it records the same configuration but ``INERT`` settings (where
    it went, how many processes). Raises ``UserError`` naming up to three settings that differ."""
    try:
        there = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return  # no report, or a damaged one: nothing a new run could lose
    if not isinstance(there, dict) or there.get(COMPLETE) is not True or not isinstance(there.get("config"), dict):
        return
    mine = {k: v for k, v in json.loads(json.dumps(config)).items() if k not in INERT}
    stored = {k: v for k, v in there["config"].items() if k not in INERT}
    diff = config_differences(mine, stored)
    if diff:
        raise UserError(
            f"{path.parent} holds a `ttompc evaluate {kind}` report of another configuration ({'; '.join(diff[:3])})",
            "pass another out=, or delete the report to replace it",
        )
