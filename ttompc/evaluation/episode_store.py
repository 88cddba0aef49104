"""The episodes of a closed-loop sweep, persisted as they finish, so that an interrupted ``ttompc evaluate mpc``
resumes without redoing them (``ttompc.evaluation.closed_loop``).

A report folder holds, beside the report, ``mpc_sweep.json`` (the settings that decide an episode's numbers, the
*fingerprint*) and ``mpc_episodes.jsonl`` (one episode record a line, appended and flushed to disk as each pool
task returns). An episode is keyed by (problem, plant, horizon, method). ``EpisodeStore.open`` reads them back:

* a folder without a sweep file starts a new sweep (its fingerprint written first);
* a folder whose fingerprint differs from the run's is refused (``UserError`` naming the settings that differ), so
  episodes of another configuration are never mixed into a report;
* otherwise its records are the episodes already done (a line cut short by an interruption is dropped, and the
  file cut back to its last whole line). The grid (``problems``, ``horizons``, ``plants``) is not in the
  fingerprint: a sweep may be extended (more problems, horizons or plants) and resumes with the episodes it has.

The fingerprint is the recorded config (``dataclasses.asdict`` of the ``ClosedLoopConfig``) but ``GRID`` and
``INERT`` keys, with the resolved MPC settings, the resolved perturbed plant and the scenario's version: a preset or a
scenario default that changed between two runs is a different configuration too. Models are named as the config
names them (a zoo name, a folder): replacing a model's files under the same name is not detected.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from ttompc.errors import UserError
from ttompc.evaluation.metrics import write_json
from ttompc.evaluation.report_files import config_differences
from ttompc.evaluation.reproduce import INERT

SWEEP_FILE, EPISODES_FILE = "mpc_sweep.json", "mpc_episodes.jsonl"
GRID = ("problems", "horizons", "plants")  # what a sweep may extend when it resumes

Key = tuple[int, str, int, str]  # (problem, plant, horizon, method)


def episode_key(record: dict[str, Any]) -> Key:
    """The key of an episode record."""
    return int(record["problem"]), str(record["plant"]), int(record["horizon"]), str(record["method"])


def fingerprint(config: dict[str, Any], resolved: dict[str, Any]) -> dict[str, Any]:
    """The settings that decide an episode's numbers: ``config`` but ``GRID`` and ``INERT`` keys, and ``resolved``
    (what the config's names resolve to: settings, perturbed plant, scenario version)."""
    kept = {k: v for k, v in config.items() if k not in GRID and k not in INERT}
    return json.loads(json.dumps({**kept, "resolved": resolved}, default=_plain))  # as it reads back from the file


def _plain(x: Any) -> Any:
    """numpy scalars and arrays as Python numbers and lists (``json.dumps``' ``default``)."""
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"{type(x).__name__} is not JSON serialisable")


class EpisodeStore:
    """The episodes of one sweep in its report folder (module doc); ``done`` holds the records by key."""

    def __init__(self, out: Path, done: dict[Key, dict[str, Any]]) -> None:
        self.out = out
        self.done = done

    @classmethod
    def open(cls, out: Path, fp: dict[str, Any]) -> EpisodeStore:
        """The store of the sweep with fingerprint ``fp`` in ``out``: new, or the one there with its episodes;
        raises ``UserError`` when ``out`` holds a sweep of another fingerprint or unreadable sweep files."""
        sweep, episodes = out / SWEEP_FILE, out / EPISODES_FILE
        fresh = "pass another out=, or delete the folder to start it over"
        if not sweep.is_file():
            out.mkdir(parents=True, exist_ok=True)
            write_json(sweep, fp)
            episodes.unlink(missing_ok=True)  # episodes without their fingerprint belong to no known sweep
            return cls(out, {})
        try:
            there = json.loads(sweep.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, ValueError) as err:
            raise UserError(f"{sweep} is unreadable ({err})", fresh) from err
        diff = config_differences(fp, there) if isinstance(there, dict) else ["the whole file"]
        if diff:
            raise UserError(f"{out} holds episodes of another configuration ({'; '.join(diff[:3])})", fresh)
        return cls(out, _read_episodes(episodes))

    def add(self, records: Iterable[dict[str, Any]]) -> None:
        """Append ``records`` (one finished task's) to the episodes file and flush them to disk."""
        records = list(records)
        text = "".join(json.dumps(r, default=_plain) + "\n" for r in records)  # NaN stays NaN (Python reads it)
        with open(self.out / EPISODES_FILE, "a", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        self.done.update((episode_key(r), r) for r in records)


def _read_episodes(path: Path) -> dict[Key, dict[str, Any]]:
    """The records of an episodes file by key (a later record of a key replaces an earlier one); a last line cut
    short by an interruption is dropped and the file cut back to its whole lines."""
    if not path.is_file():
        return {}
    data = path.read_bytes()
    whole = data[: data.rfind(b"\n") + 1]
    if len(whole) != len(data):
        with open(path, "r+b") as f:
            f.truncate(len(whole))
    done: dict[Key, dict[str, Any]] = {}
    for number, line in enumerate(whole.decode("utf-8").splitlines(), 1):
        try:
            record = json.loads(line)
            done[episode_key(record)] = record
        except (ValueError, KeyError, TypeError) as err:
            raise UserError(
                f"{path}, line {number}, is not an episode record ({err})",
                "delete the folder to start the sweep over, or pass another out=",
            ) from err
    return done
