"""Model cards: ``zoo/<name>.md``, Markdown with a YAML front matter that is also Hugging Face model-card metadata.

The front matter is the machine-readable record (what ``zoo/index.json`` is generated from); the Markdown body is
for people, with the full tables. Parsing is strict (unknown keys, bad hashes, unsafe names are errors) because the
card decides which bytes land in a user's cache and under which file names.

Numbers live in ``evaluations``: ``{name: {command, what, metrics: {key: value}}}``, each evaluation's command (how to
reproduce its numbers) stated once. Besides our record the rendered front matter carries the Hub's keys:
``library_name: ttompc``, ``license``, ``tags``, ``datasets`` (Hub ids of the training data), ``base_model`` (the
source of a fine-tuned model) and a ``model-index`` that ``huggingface_hub.ModelCard.load(...).data.eval_results``
reads: the headline results only (``headline_metrics``), one per evaluation that has them, derived from
``evaluations``. A card whose ``model-index`` states a number its evaluations do not hold is refused, so the numbers
the Hub shows are the card's. Cards of the first format (``metrics: {key: {value, how}}``, the command repeated in
every ``how``) still load (``evaluations_from_metrics``).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from ttompc.errors import UserError

KINDS = ("TTO", "FT-TTO")  # pre-trained transformer / DAgger fine-tuned transformer
LIBRARY_NAME = "ttompc"
INFERENCE_KEYS = ("rtg_scale", "conditioning")  # what the card's ``inference`` section may hold
# the Hub tasks of the model-index results: an open-loop (warm start) and a closed-loop (MPC) evaluation's headline
WARMSTART_TASK = {"type": "trajectory-optimization", "name": "Open-loop warm start of full-horizon SCP"}
MPC_TASK = {"type": "model-predictive-control", "name": "Closed-loop TTO-MPC"}
REQUIRED_FILES = ("model.safetensors", "config.json")
# Names become directory and file names in the cache: one path component, no leading dot, no "..".
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")
_SHA256_RE = re.compile(r"^[0-9a-f]{64}$")
_OPTIONAL_HUB_KEYS = ("datasets", "base_model", "inference")
_HUB_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,95}/[A-Za-z0-9][A-Za-z0-9._-]{0,95}$")
_FRONT_MATTER_RE = re.compile(r"\A---[ \t]*\r?\n(.*?)\r?\n---[ \t]*(?:\r?\n|\Z)(.*)\Z", re.DOTALL)
_MODEL_MPC_RE = re.compile(r"mpc(\d+)_nominal_(model|robust)_feasible_rate")
_REL_MPC_RE = re.compile(r"mpc(\d+)_nominal_rel_feasible_rate")
_LEGACY_COMMAND_RE = re.compile(r"`([^`]+)`")  # the command a first-format ``how`` starts with


class CardError(UserError, ValueError):
    """A model card (or a name in one) that does not match the format."""


def validate_name(name: str, what: str = "model name") -> str:
    """``name`` if it is a safe single path component, else ``CardError`` (blocks ``../x``, ``a/b``, ``.hidden``)."""
    if not isinstance(name, str) or not _NAME_RE.fullmatch(name) or ".." in name:
        raise CardError(
            f"invalid {what} {name!r}: use 1-100 characters from [A-Za-z0-9._-], starting with a letter or digit, "
            "without '..'"
        )
    return name


def validate_sha256(digest: str) -> str:
    if not isinstance(digest, str) or not _SHA256_RE.fullmatch(digest):
        raise CardError(f"invalid sha256 {digest!r}: expected 64 lowercase hex digits")
    return digest


@dataclass(frozen=True)
class FileEntry:
    """One published file: where to fetch it and the exact bytes expected (sha256 + size)."""

    filename: str
    url: str
    sha256: str
    size: int

    def __post_init__(self) -> None:
        validate_name(self.filename, "file name")
        validate_sha256(self.sha256)
        if not isinstance(self.url, str) or not self.url:
            raise CardError(f"file {self.filename!r}: url must be a non-empty string")
        if not isinstance(self.size, int) or isinstance(self.size, bool) or self.size < 0:
            raise CardError(f"file {self.filename!r}: size must be a non-negative integer, got {self.size!r}")

    def to_dict(self) -> dict[str, Any]:
        return {"filename": self.filename, "url": self.url, "sha256": self.sha256, "size": self.size}


@dataclass
class ModelCard:
    """The front matter of ``zoo/<name>.md`` (``body`` is the Markdown after it)."""

    name: str
    kind: str
    scenario: str
    scenario_version: str | int
    architecture: dict[str, Any]
    recipe: str
    data_card: str
    files: list[FileEntry]
    code_version: str
    evaluations: dict[str, dict[str, Any]] = field(default_factory=dict)
    license: str = "mit"
    tags: list[str] = field(default_factory=list)
    datasets: list[str] = field(default_factory=list)
    base_model: str = ""
    inference: dict[str, Any] = field(default_factory=dict)
    body: str = ""

    def __post_init__(self) -> None:
        validate_name(self.name)
        if self.kind not in KINDS:
            raise CardError(f"card {self.name!r}: kind must be one of {KINDS}, got {self.kind!r}")
        if not isinstance(self.architecture, dict):
            raise CardError(f"card {self.name!r}: architecture must be a mapping")
        try:
            self.evaluations = validate_evaluations(self.evaluations)
        except CardError as err:
            raise CardError(f"card {self.name!r}: {err}") from None
        names = [f.filename for f in self.files]
        missing = [f for f in REQUIRED_FILES if f not in names]
        if missing or len(set(names)) != len(names):
            raise CardError(f"card {self.name!r}: files must list {REQUIRED_FILES} once each, got {names}")
        bad = [d for d in self.datasets if not _HUB_ID_RE.fullmatch(d) or ".." in d]
        if bad:
            raise CardError(f"card {self.name!r}: datasets must be Hugging Face ids ORG/NAME, got {bad}")
        if self.base_model and (self.kind != "FT-TTO" or not _HUB_ID_RE.fullmatch(self.base_model)):
            raise CardError(
                f"card {self.name!r}: base_model {self.base_model!r} must be the Hugging Face id ORG/NAME of the "
                f"model a fine-tuned (FT-TTO) model started from; this one is {self.kind}"
            )
        if not isinstance(self.inference, dict) or not set(self.inference) <= set(INFERENCE_KEYS):
            raise CardError(f"card {self.name!r}: inference must be a mapping with keys from {INFERENCE_KEYS}")

    @property
    def size(self) -> int:
        return sum(f.size for f in self.files)

    @property
    def metrics(self) -> dict[str, int | float]:
        """Every number of every evaluation, by key (a key is in one evaluation only)."""
        return {k: v for e in self.evaluations.values() for k, v in e["metrics"].items()}

    def to_dict(self) -> dict[str, Any]:
        """Front-matter mapping (also one entry of ``index.json``); key order is the documented card order."""
        return {
            "name": self.name,
            "kind": self.kind,
            "scenario": {"name": self.scenario, "version": self.scenario_version},
            "architecture": self.architecture,
            "recipe": self.recipe,
            "data_card": self.data_card,
            "files": [f.to_dict() for f in self.files],
            "license": self.license,
            "code_version": self.code_version,
            "tags": self.tags,
            "datasets": self.datasets,
            "base_model": self.base_model,
            "inference": self.inference,
            "evaluations": self.evaluations,
        }

    def front_matter(self) -> dict[str, Any]:
        """The record (``to_dict``) plus the Hub's derived keys; empty optional Hub keys are left out."""
        record = {k: v for k, v in self.to_dict().items() if v or k not in _OPTIONAL_HUB_KEYS}
        index = self.model_index()
        return {"library_name": LIBRARY_NAME, **record, **({"model-index": index} if index else {})}

    def model_index(self) -> list[dict[str, Any]]:
        """The Hub's ``model-index``: one result per evaluation with a headline (``headline_metrics``), its dataset's
        ``config`` naming the evaluation; empty when no evaluation has one. The other numbers and the commands stay
        in ``evaluations`` (the Hub's result format has no place for a command)."""
        results = []
        for name, evaluation in self.evaluations.items():
            headline = headline_metrics(evaluation["metrics"], self.kind)
            if headline is None:
                continue
            task, keys = headline
            dataset = {
                "type": f"{LIBRARY_NAME}/{self.scenario}",
                "name": f"{self.scenario} v{self.scenario_version} held-out problems",
                "config": name,
            }
            metrics = [{"name": label, "type": key, "value": evaluation["metrics"][key]} for key, label in keys]
            results.append({"task": dict(task), "dataset": dataset, "metrics": metrics})
        return [{"name": self.name, "results": results}] if results else []

    @classmethod
    def from_dict(cls, d: dict[str, Any], body: str = "") -> ModelCard:
        """The card of the front matter ``d`` (either format), checked; ``CardError`` names what is wrong."""
        if not isinstance(d, dict):
            raise CardError("card front matter must be a YAML mapping")
        d = _from_first_format(d)
        allowed = {
            "name",
            "kind",
            "scenario",
            "architecture",
            "recipe",
            "data_card",
            "evaluations",
            "files",
            "license",
            "code_version",
            "tags",
            "datasets",
            "base_model",
            "inference",
            "library_name",
            "model-index",
        }
        unknown = sorted(set(d) - allowed)
        required = sorted({"name", "kind", "scenario", "architecture", "files", "code_version"} - set(d))
        if unknown or required:
            raise CardError(f"card {d.get('name')!r}: unknown keys {unknown}, missing keys {required}")
        scenario = d["scenario"]
        if not isinstance(scenario, dict) or set(scenario) != {"name", "version"}:
            raise CardError(f"card {d['name']!r}: scenario must be a mapping with exactly 'name' and 'version'")
        files = d["files"]
        if not isinstance(files, list) or not all(isinstance(f, dict) for f in files):
            raise CardError(f"card {d['name']!r}: files must be a list of mappings")
        try:
            entries = [FileEntry(**f) for f in files]
        except TypeError as err:
            raise CardError(f"card {d['name']!r}: bad file entry ({err})") from None
        if d.get("library_name", LIBRARY_NAME) != LIBRARY_NAME:
            raise CardError(f"card {d['name']!r}: library_name must be {LIBRARY_NAME!r}, got {d['library_name']!r}")
        card = cls(
            name=d["name"],
            kind=d["kind"],
            scenario=str(scenario["name"]),
            scenario_version=scenario["version"],
            architecture=d["architecture"],
            recipe=str(d.get("recipe", "")),
            data_card=str(d.get("data_card", "")),
            files=entries,
            code_version=str(d["code_version"]),
            evaluations=d.get("evaluations") or {},
            license=str(d.get("license", "mit")),
            tags=[str(t) for t in d.get("tags") or []],
            datasets=[str(t) for t in d.get("datasets") or []],
            base_model=str(d.get("base_model") or ""),
            inference=d.get("inference") or {},
            body=body,
        )
        metrics = card.metrics
        stated = _model_index_values(d["model-index"]) if "model-index" in d else []
        wrong = sorted({str(k) for k, v in stated if not isinstance(k, str) or k not in metrics or metrics[k] != v})
        if wrong:
            raise CardError(
                f"card {d['name']!r}: model-index does not match the evaluations' metrics ({', '.join(wrong)})",
                "edit evaluations only and re-render the card (the model-index is derived from them)",
            )
        return card


def _model_index_values(index: Any) -> list[tuple[Any, Any]]:
    """(type, value) of every metric of a Hub ``model-index``; ``CardError`` when it does not have that shape."""
    try:
        return [(m["type"], m["value"]) for entry in index for r in entry["results"] for m in r["metrics"]]
    except (TypeError, KeyError):
        raise CardError(
            "model-index must be a Hub model-index: [{name, results: [{task, dataset, metrics}]}]"
        ) from None


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


def _from_first_format(d: dict[str, Any]) -> dict[str, Any]:
    """A front matter of the first card format (``metrics: {key: {value, how}}``, ``headline_metrics``,
    ``inference.protocol``: the commands again) in today's, so cards published before the change (on the Hub, in a
    user's zoo) still load; a current one as given."""
    if "metrics" not in d and "headline_metrics" not in d:
        return d
    if "evaluations" in d:
        raise CardError(f"card {d.get('name')!r}: metrics (the first card format) and evaluations: keep evaluations")
    out = {k: v for k, v in d.items() if k not in ("metrics", "headline_metrics")}
    out["evaluations"] = evaluations_from_metrics(d.get("metrics") or {})
    if isinstance(d.get("inference"), dict):
        out["inference"] = {k: v for k, v in d["inference"].items() if k != "protocol"}
    return out


def parse_card(text: str) -> ModelCard:
    match = _FRONT_MATTER_RE.match(text)
    if match is None:
        raise CardError("a model card must start with a YAML front matter block between '---' lines")
    try:
        front = yaml.safe_load(match.group(1))
    except yaml.YAMLError as err:
        raise CardError(f"card front matter is not valid YAML: {err}") from None
    return ModelCard.from_dict(front, body=match.group(2))


def render_card(card: ModelCard) -> str:
    """The card file: its front matter, with mappings and lists of plain values in flow style (``{...}``, ``[...]``:
    an evaluation's metrics read as one paragraph, not a line each), then its body."""
    front = yaml.safe_dump(card.front_matter(), sort_keys=False, allow_unicode=True, default_flow_style=None, width=110)
    return f"---\n{front}---\n{card.body}"


def read_card(path: Path) -> ModelCard:
    """Parse ``path`` and check that the card's name matches its file name (``zoo/<name>.md``)."""
    try:
        card = parse_card(path.read_text(encoding="utf-8"))
    except CardError as err:
        raise CardError(f"{path}: {err}") from None
    if card.name != path.stem:
        raise CardError(f"{path}: card name {card.name!r} must match the file name {path.stem!r}")
    return card
