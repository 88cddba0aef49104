"""Model cards: ``zoo/<name>.md``, Markdown with a YAML front matter that is also Hugging Face model-card metadata.

The front matter is the machine-readable record (what ``zoo/index.json`` is generated from); the Markdown body is
for people. Parsing is strict (unknown keys, bad hashes, unsafe names are errors) because the card decides which
bytes land in a user's cache and under which file names.

Besides our record the rendered front matter carries the Hub's keys: ``library_name: ttompc``, ``license``,
``tags``, ``datasets`` (Hub ids of the training data), ``base_model`` (the source of a fine-tuned model) and a
``model-index`` that ``huggingface_hub.ModelCard.load(...).data.eval_results`` reads. The ``model-index`` is derived
from ``metrics`` (open-loop ``ws_*`` and closed-loop ``mpc*`` metrics, one result each); a card whose
``model-index`` differs from its metrics is refused, so the numbers the Hub shows are the card's.
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
INFERENCE_KEYS = ("rtg_scale", "conditioning", "protocol")  # what the card's ``inference`` section may hold
# model-index results: metric-name prefix -> (task type, task name)
EVAL_TASKS = {
    "ws_": ("trajectory-optimization", "Open-loop warm start of full-horizon SCP"),
    "mpc": ("model-predictive-control", "Closed-loop TTO-MPC"),
}
REQUIRED_FILES = ("model.safetensors", "config.json")
# Names become directory and file names in the cache: one path component, no leading dot, no "..".
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")
_SHA256_RE = re.compile(r"^[0-9a-f]{64}$")
_OPTIONAL_HUB_KEYS = ("datasets", "base_model", "inference")
_HUB_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,95}/[A-Za-z0-9][A-Za-z0-9._-]{0,95}$")
_FRONT_MATTER_RE = re.compile(r"\A---[ \t]*\r?\n(.*?)\r?\n---[ \t]*(?:\r?\n|\Z)(.*)\Z", re.DOTALL)


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
    metrics: dict[str, dict[str, Any]] = field(default_factory=dict)
    headline_metrics: list[str] = field(default_factory=list)
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
        self.metrics = validate_metrics(self.metrics)
        unknown = [m for m in self.headline_metrics if m not in self.metrics]
        if unknown:
            raise CardError(f"card {self.name!r}: headline_metrics {unknown} are not in metrics")
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

    def headline(self) -> dict[str, Any]:
        """The metrics to show in ``ttompc zoo list``: ``headline_metrics`` if set, else the first two."""
        keys = self.headline_metrics or list(self.metrics)[:2]
        return {k: self.metrics[k]["value"] for k in keys}

    def to_dict(self) -> dict[str, Any]:
        """Front-matter mapping (also one entry of ``index.json``); key order is the documented card order."""
        return {
            "name": self.name,
            "kind": self.kind,
            "scenario": {"name": self.scenario, "version": self.scenario_version},
            "architecture": self.architecture,
            "recipe": self.recipe,
            "data_card": self.data_card,
            "metrics": self.metrics,
            "headline_metrics": self.headline_metrics,
            "files": [f.to_dict() for f in self.files],
            "license": self.license,
            "code_version": self.code_version,
            "tags": self.tags,
            "datasets": self.datasets,
            "base_model": self.base_model,
            "inference": self.inference,
        }

    def front_matter(self) -> dict[str, Any]:
        """The record (``to_dict``) plus the Hub's derived keys; empty optional Hub keys are left out."""
        record = {k: v for k, v in self.to_dict().items() if v or k not in _OPTIONAL_HUB_KEYS}
        index = self.model_index()
        return {"library_name": LIBRARY_NAME, **record, **({"model-index": index} if index else {})}

    def model_index(self) -> list[dict[str, Any]]:
        """The Hub's ``model-index`` derived from ``metrics``: one result per evaluation (``EVAL_TASKS``: open loop,
        closed loop) holding its metrics' values; empty when the card has no such metric. How each number was
        measured stays in ``metrics`` (the Hub's result format has no place for it)."""
        results = []
        for prefix, (task_type, task_name) in EVAL_TASKS.items():
            metrics = [{"type": k, "value": m["value"]} for k, m in self.metrics.items() if k.startswith(prefix)]
            if metrics:
                dataset = {
                    "type": f"{LIBRARY_NAME}/{self.scenario}",
                    "name": f"{self.scenario} v{self.scenario_version} held-out problems",
                }
                results.append({"task": {"type": task_type, "name": task_name}, "dataset": dataset, "metrics": metrics})
        return [{"name": self.name, "results": results}] if results else []

    @classmethod
    def from_dict(cls, d: dict[str, Any], body: str = "") -> ModelCard:
        if not isinstance(d, dict):
            raise CardError("card front matter must be a YAML mapping")
        allowed = {
            "name",
            "kind",
            "scenario",
            "architecture",
            "recipe",
            "data_card",
            "metrics",
            "headline_metrics",
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
            metrics=d.get("metrics") or {},
            headline_metrics=list(d.get("headline_metrics") or []),
            license=str(d.get("license", "mit")),
            tags=[str(t) for t in d.get("tags") or []],
            datasets=[str(t) for t in d.get("datasets") or []],
            base_model=str(d.get("base_model") or ""),
            inference=d.get("inference") or {},
            body=body,
        )
        if "model-index" in d and d["model-index"] != card.model_index():
            raise CardError(
                f"card {d['name']!r}: model-index does not match metrics",
                "edit metrics only and re-render the card (the model-index is derived from them)",
            )
        return card


def is_metric_value(x: Any) -> bool:
    """A reportable metric value: a finite int or float (not a bool)."""
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def validate_metrics(metrics: Any) -> dict[str, dict[str, Any]]:
    """Each metric is ``{value: number, how: str, ...}``: a number without how it was measured is not reportable."""
    if not isinstance(metrics, dict):
        raise CardError(f"metrics must be a mapping of name -> {{value, how}}, got {type(metrics).__name__}")
    for key, m in metrics.items():
        ok = isinstance(m, dict) and "value" in m and isinstance(m.get("how"), str) and m["how"].strip()
        value = m.get("value") if isinstance(m, dict) else None
        if not ok or not is_metric_value(value):
            raise CardError(f"metric {key!r} must be {{value: finite number, how: non-empty text}}, got {m!r}")
    return metrics


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
    front = yaml.safe_dump(
        card.front_matter(), sort_keys=False, allow_unicode=True, default_flow_style=False, width=110
    )
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
