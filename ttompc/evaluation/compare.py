"""Pairing closed-loop reports made on the same held-out problems (``ttompc evaluate compare BASE OTHER ...``).

Contract. A report is a folder written by ``ttompc evaluate mpc`` (its ``mpc_runs.csv`` and ``mpc.json``) or the
path of such an ``mpc_runs.csv``, complete (``report_files.read_report``: its ``mpc.json`` marked complete); it is
labelled by its folder name (the path as given when two reports share a folder name). Runs are matched on (plant,
method, horizon, problem). For every other report and every (plant, method, horizon) that both it and the base ran
(optionally only ``methods`` and ``horizons``), one row (``compare_reports``) over the problems both ran:

* ``problems``: how many; ``base_goals`` / ``other_goals``: feasible episodes among them; ``lost``: feasible in the
  base, not in the other; ``won``: the reverse;
* ``paired``: other − base in (J − J_REL)/J_REL, in points (×100), over the problems both ran feasibly:
  ``stats.interval`` (mean, standard error with ddof=1, 95% bootstrap interval lo/hi, n); negative: the other is
  cheaper;
* ``step_ratio``: mean step time of the base / of the other over the problems both ran, feasible or not (> 1: the
  other steps faster);

all of them ``stats.paired``'s, the comparison the closed-loop report and the demo make too.

Refused with a ``UserError`` (one line, what to do): a report that cannot be read or is not complete, two reports
whose ``mpc.json`` configs differ in scenario or seed, a matched run whose per-problem ``seed`` differs (not the
same held-out problem), and two reports with no (plant, method, horizon) in common. ``format_comparison`` renders the
rows as a markdown table. Only the standard library, numpy, ``stats`` and ``report_files`` are imported (no solver,
no torch).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ttompc.errors import UserError
from ttompc.evaluation.report_files import read_report
from ttompc.evaluation.stats import Outcome, format_interval, paired

RUNS_FILE, CONFIG_FILE = "mpc_runs.csv", "mpc.json"
COLUMNS = ("problem", "seed", "method", "horizon", "plant", "rel_increment", "feasible", "mean_step_time")
_WHAT = "pass a report folder of `ttompc evaluate mpc` or its mpc_runs.csv"

Key = tuple[str, str, int]  # (plant, method, horizon)


@dataclass(frozen=True)
class Run:
    """One closed-loop episode of a report: its problem's seed and what the comparison reads of its CSV row."""

    seed: str
    outcome: Outcome


@dataclass
class Report:
    """A closed-loop report: its runs by (plant, method, horizon) and problem, and its ``mpc.json`` config (None when
    it records none)."""

    path: Path
    label: str
    runs: dict[Key, dict[int, Run]] = field(default_factory=dict)
    config: dict[str, Any] | None = None


def _bool(text: str) -> bool:
    value = text.strip().lower()
    if value in ("true", "1"):
        return True
    if value in ("false", "0"):
        return False
    raise ValueError(f"feasible={text!r} is not True or False")


def load_report(path: str | Path, label: str | None = None) -> Report:
    """Read a complete report folder (or its ``mpc_runs.csv``) with its ``mpc.json``."""
    given = Path(path)
    csv_path = given / RUNS_FILE if given.is_dir() else given
    if not csv_path.is_file():
        raise UserError(f"no closed-loop report at {given} ({csv_path} not found)", _WHAT)
    report = Report(path=given, label=label or csv_path.parent.resolve().name)
    config = read_report(csv_path.parent / CONFIG_FILE, "mpc").get("config")  # refuses an incomplete report
    report.config = dict(config) if isinstance(config, dict) else None
    with open(csv_path, newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        missing = [c for c in COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise UserError(f"{csv_path} lacks the column(s) {', '.join(missing)}", _WHAT)
        for line, row in enumerate(reader, 2):
            try:
                key = (row["plant"], row["method"], int(row["horizon"]))
                problem = int(row["problem"])
                run = Run(
                    seed=row["seed"].strip(),
                    outcome=Outcome(
                        feasible=_bool(row["feasible"]),
                        rel_increment=float(row["rel_increment"] or "nan"),
                        step_time=float(row["mean_step_time"] or "nan"),
                    ),
                )
            except (ValueError, TypeError) as err:
                raise UserError(f"{csv_path}, line {line}: unreadable run ({err})", _WHAT) from err
            group = report.runs.setdefault(key, {})
            if problem in group:
                raise UserError(
                    f"{csv_path} has two runs of problem {problem} for {_name(key)}",
                    "compare one report per folder, not concatenated CSVs",
                )
            group[problem] = run
    return report


def _name(key: Key) -> str:
    return f"{key[1]} at H = {key[2]} on the {key[0]} plant"


def _labels(paths: Sequence[str | Path]) -> list[str]:
    """Folder names, or the paths as given where two folder names coincide."""
    names = [(Path(p) if Path(p).is_dir() else Path(p).parent).resolve().name for p in paths]
    return [n if names.count(n) == 1 else str(p) for n, p in zip(names, paths, strict=True)]


def _check_configs(base: Report, other: Report) -> None:
    if base.config is None or other.config is None:
        return
    for key in ("scenario", "seed"):
        a, b = base.config.get(key), other.config.get(key)
        if a != b:
            raise UserError(
                f"{base.label} and {other.label} were measured on different problems ({key} {a} vs {b} in their "
                f"{CONFIG_FILE})",
                "compare reports of `ttompc evaluate mpc` run with the same scenario and seed",
            )


def _pair(base: Report, other: Report, key: Key, seed: int) -> dict[str, Any]:
    b, o = base.runs[key], other.runs[key]
    problems = sorted(set(b) & set(o))
    for p in problems:
        if b[p].seed != o[p].seed:
            raise UserError(
                f"problem {p} of {_name(key)} has seed {b[p].seed} in {base.label} but {o[p].seed} in {other.label}: "
                "not the same held-out problem",
                "compare reports of `ttompc evaluate mpc` run with the same scenario and seed",
            )
    pair = paired({p: b[p].outcome for p in problems}, {p: o[p].outcome for p in problems}, scale=100, seed=seed)
    return {"base": base.label, "other": other.label, "plant": key[0], "method": key[1], "horizon": key[2], **pair}


def compare_reports(
    base: str | Path,
    others: Sequence[str | Path],
    *,
    methods: Sequence[str] | None = None,
    horizons: Sequence[int] | None = None,
    seed: int = 0,
) -> list[dict[str, Any]]:
    """The rows of the module's contract: for each of ``others`` (in order), each (plant, method, horizon) it shares
    with ``base`` (plants sorted, methods in the base's order, horizons ascending), optionally only ``methods`` and
    ``horizons``. ``seed`` seeds the bootstrap."""
    if not others:
        raise UserError("nothing to compare", "pass a base report and at least one other")
    labels = _labels([base, *others])
    reference = load_report(base, labels[0])
    order = list(dict.fromkeys(m for _, m, _ in reference.runs))  # methods in the base's order
    rows = []
    for path, label in zip(others, labels[1:], strict=True):
        other = load_report(path, label)
        _check_configs(reference, other)
        common = [
            key
            for key in reference.runs
            if key in other.runs and (methods is None or key[1] in methods) and (horizons is None or key[2] in horizons)
        ]
        if not common:
            wanted = "".join(
                f" among {name} {','.join(map(str, v))}"
                for name, v in (("methods", methods), ("horizons", horizons))
                if v is not None
            )
            ran = ", ".join(dict.fromkeys(f"{m}@{h}" for _, m, h in reference.runs))
            raise UserError(
                f"{reference.label} and {other.label} share no (plant, method, horizon){wanted}; "
                f"{reference.label} ran {ran}",
                "compare reports of the same methods and horizons (or widen --methods/--horizons)",
            )
        common.sort(key=lambda k: (k[0], order.index(k[1]), k[2]))
        rows += [_pair(reference, other, key, seed) for key in common]
    return rows


def format_comparison(rows: Sequence[dict[str, Any]]) -> str:
    """A markdown table of ``compare_reports`` (about 120 columns wide): one block per other report."""
    if not rows:
        return ""
    base = rows[0]["base"]
    lines = []
    for label in dict.fromkeys(r["other"] for r in rows):
        lines += [
            f"### {label} against {base}, paired on the same problems\n",
            "| plant | method | H | goals base → other | lost / won | Δ (J − J_REL)/J_REL, points (n) "
            "| step time base/other |",
            "|---|---|---|---|---|---|---|",
        ]
        for r in (r for r in rows if r["other"] == label):
            iv = r["paired"]
            paired = f"{format_interval(iv)} ({iv['n']})" if iv["n"] else "–"
            ratio = f"{r['step_ratio']:.2f}×" if math.isfinite(r["step_ratio"]) else "–"
            lines.append(
                f"| {r['plant']} | {r['method']} | {r['horizon']} | {r['base_goals']} → {r['other_goals']} "
                f"/ {r['problems']} | {r['lost']} / {r['won']} | {paired} | {ratio} |"
            )
        lines.append("")
    lines.append(
        "Goals: feasible episodes among the problems both reports ran; lost: feasible in the base only, won: in the\n"
        "other only. Δ: mean ± s.e. [95% bootstrap CI] of other − base over the n problems both ran feasibly\n"
        "(negative: the other is cheaper). Step time ratio > 1: the other steps faster."
    )
    return "\n".join(lines)
