"""A card's numbers: its *evaluations*, ``{name: {command, what, metrics: {key: number}}}``, each evaluation's command
(how to reproduce its numbers) stated once. They live in the card's metrics file (``metrics.json``, published beside
the bundle and listed with its sha256 in the card's ``files``), at full precision, in the format ``ttompc zoo
metrics`` writes; the card shows its headline (``headline_metrics``) in the Hub's ``model-index``, rounded to the
standard errors (``ttompc.zoo.rounding``).

Cards of the first format kept every metric in the front matter as ``metrics: {key: {value, how}}``, the command
repeated in every ``how``; ``evaluations_from_metrics`` groups them by command.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

from ttompc.zoo.errors import CardError
from ttompc.zoo.rounding import rounded

METRICS_FILE = "metrics.json"  # the evaluations beside the bundle
# the Hub tasks of the model-index results: an open-loop (warm start) and a closed-loop (MPC) evaluation's headline
WARMSTART_TASK = {"type": "trajectory-optimization", "name": "Open-loop warm start of full-horizon SCP"}
MPC_TASK = {"type": "model-predictive-control", "name": "Closed-loop TTO-MPC"}
_MODEL_MPC_RE = re.compile(r"mpc(\d+)_nominal_(model|robust)_feasible_rate")
_REL_MPC_RE = re.compile(r"mpc(\d+)_nominal_rel_feasible_rate")
_LEGACY_COMMAND_RE = re.compile(r"`([^`]+)`")  # the command a first-format ``how`` starts with


def is_metric_value(x: Any) -> bool:
    """A reportable metric value: a finite int or float (not a bool)."""
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def validate_evaluations(evaluations: Any) -> dict[str, dict[str, Any]]:
    """``evaluations`` as ``{name: {command, what, metrics}}`` in that key order (``what`` left out when empty), or
    ``CardError``. Each evaluation has a non-empty ``command`` (how to reproduce its numbers: a number without it is
    not reportable), an optional one-line ``what`` and ``metrics: {key: finite number}``; a key is in one evaluation
    only."""
    if not isinstance(evaluations, dict):
        raise CardError(f"evaluations must be a mapping of name -> {{command, what, metrics}}, got {evaluations!r}")
    out: dict[str, dict[str, Any]] = {}
    for name, e in evaluations.items():
        ok = (
            isinstance(name, str)
            and name
            and isinstance(e, dict)
            and set(e) <= {"command", "what", "metrics"}
            and isinstance(e.get("command"), str)
            and e["command"].strip()
            and isinstance(e.get("what", ""), str)
            and isinstance(e.get("metrics", {}), dict)
        )
        if not ok:
            raise CardError(
                f"evaluation {name!r} must be {{command: non-empty text, what: text, metrics: {{key: number}}}}, "
                f"got {e!r}"
            )
        metrics = e.get("metrics", {})
        bad = [k for k, v in metrics.items() if not isinstance(k, str) or not is_metric_value(v)]
        twice = sorted(k for k in metrics if any(k in o["metrics"] for o in out.values()))
        if bad or twice:
            raise CardError(
                f"evaluation {name!r}: metrics {bad} are not finite numbers, {twice} are in another evaluation too"
            )
        out[name] = {
            "command": e["command"],
            **({"what": e["what"]} if e.get("what") else {}),
            "metrics": dict(metrics),
        }
    return out


def evaluations_from_metrics(metrics: Any) -> dict[str, dict[str, Any]]:
    """The first card format's ``metrics: {key: {value, how}}`` as evaluations: a metric goes to the evaluation of the
    command quoted at the start of its ``how`` (the whole ``how`` when it quotes none), named after its
    ``ttompc evaluate`` kind (``warmstart``, ``mpc``; ``mpc_2`` for a second one), else ``eval``."""
    if not isinstance(metrics, dict):
        raise CardError(f"metrics must be a mapping of name -> {{value, how}}, got {type(metrics).__name__}")
    by_command: dict[str, dict[str, Any]] = {}
    for key, m in metrics.items():
        ok = isinstance(m, dict) and isinstance(m.get("how"), str) and m["how"].strip()
        if not ok or not is_metric_value(m.get("value")):
            raise CardError(f"metric {key!r} must be {{value: finite number, how: non-empty text}}, got {m!r}")
        quoted = _LEGACY_COMMAND_RE.match(m["how"])
        command = quoted.group(1) if quoted else m["how"]
        by_command.setdefault(command, {"command": command, "metrics": {}})["metrics"][key] = m["value"]
    out: dict[str, dict[str, Any]] = {}
    for command, evaluation in by_command.items():
        words = command.split()
        base = words[2] if len(words) > 2 and words[:2] == ["ttompc", "evaluate"] else "eval"
        name, i = base, 1
        while name in out:
            i += 1
            name = f"{base}_{i}"
        out[name] = evaluation
    return out


def headline_metrics(metrics: dict[str, int | float], kind: str) -> tuple[dict[str, str], list[tuple[str, str]]] | None:
    """The headline of one evaluation's ``metrics`` of a ``kind`` model, as (Hub task, [(metric key, its name)]);
    None when it has none. Open loop: (J - J_REL)/J_REL and SCP iterations of SCP warm-started by the model and by
    REL. Closed loop, nominal plant, at the shortest horizon the model ran: goals reached and (J - J_REL)/J_REL of
    its better variant (more goals, then cheaper: TTO-MPC or the robust R-TTO-MPC) and of REL-MPC at each horizon
    the evaluation ran it."""
    if "ws_suboptimality" in metrics:
        names = {
            "ws_suboptimality": f"(J - J_REL)/J_REL, SCP from the {kind} warm start",
            "ws_suboptimality_rel": "(J - J_REL)/J_REL, SCP from the REL warm start",
            "ws_iterations": f"SCP iterations from the {kind} warm start",
            "ws_iterations_rel": "SCP iterations from the REL warm start",
        }
        return WARMSTART_TASK, [(k, name) for k, name in names.items() if k in metrics]
    runs = [(int(m.group(1)), m.group(2)) for m in map(_MODEL_MPC_RE.fullmatch, metrics) if m]
    if not runs:
        return None
    horizon = min(h for h, _ in runs)

    def rank(variant: str) -> tuple[float, float]:
        key = f"mpc{horizon}_nominal_{variant}"
        return -metrics[f"{key}_feasible_rate"], metrics.get(f"{key}_rel_increment", math.inf)

    best = min((v for h, v in runs if h == horizon), key=rank)
    label = f"{kind}-MPC" if best == "model" else f"R-{kind}-MPC"
    rows = [(f"mpc{horizon}_nominal_{best}", f"{label}@{horizon}")]
    rel = sorted(int(m.group(1)) for m in map(_REL_MPC_RE.fullmatch, metrics) if m)
    rows += [(f"mpc{h}_nominal_rel", f"REL-MPC@{h}") for h in rel]
    keys = []
    for key, label in rows:
        keys.append((f"{key}_feasible_rate", f"{label}: goals reached, nominal plant"))
        if f"{key}_rel_increment" in metrics:
            keys.append((f"{key}_rel_increment", f"{label}: (J - J_REL)/J_REL, nominal plant"))
    return MPC_TASK, keys


def index_mismatches(stated: list[tuple[Any, Any]], evaluations: dict[str, dict[str, Any]]) -> list[str]:
    """The metric keys of a model-index's (key, value) pairs whose value is neither the evaluations' number nor that
    number rounded to its standard error (what ``ModelCard.model_index`` writes), sorted."""
    owner = {k: e["metrics"] for e in evaluations.values() for k in e["metrics"]}
    wrong = set()
    for key, value in stated:
        metrics = owner.get(key) if isinstance(key, str) else None
        if metrics is None or value not in (metrics[key], rounded(metrics, key)):
            wrong.add(str(key))
    return sorted(wrong)


def encode_evaluations(evaluations: dict[str, dict[str, Any]]) -> bytes:
    """The metrics file's bytes: the evaluations as indented JSON (full precision), one trailing newline."""
    return (json.dumps(validate_evaluations(evaluations), indent=2, ensure_ascii=False) + "\n").encode("utf-8")


def decode_evaluations(data: bytes, what: str) -> dict[str, dict[str, Any]]:
    """The evaluations in a metrics file's bytes (``what`` names the file in errors), or ``CardError``."""
    try:
        return validate_evaluations(json.loads(data.decode("utf-8")))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise CardError(f"{what} is not a JSON metrics file: {err}") from None
    except CardError as err:
        raise CardError(f"{what}: {err}") from None


def load_metrics(path: str | Path) -> dict[str, dict[str, Any]]:
    """The evaluations in a JSON file (``--card-metrics``): ``{name: {command, what, metrics}}`` as ``ttompc zoo
    metrics`` writes it (a card's metrics file is one too), or the first format's ``{key: {value, how}}``."""
    with open(path, encoding="utf-8") as fh:
        data = json.load(fh)
    first_format = isinstance(data, dict) and any(isinstance(m, dict) and "how" in m for m in data.values())
    return validate_evaluations(evaluations_from_metrics(data) if first_format else data)
