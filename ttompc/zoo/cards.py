"""Model cards: ``zoo/<name>.md``, Markdown with a YAML front matter that is also Hugging Face model-card metadata.

The front matter is the machine-readable record (what ``zoo/index.json`` is generated from); the Markdown body is
for people, with the tables. Parsing is strict (unknown keys, bad hashes, unsafe names are errors) because the card
decides which bytes land in a user's cache and under which file names.

The numbers are not in the front matter: ``evaluations: metrics.json`` names the card's metrics file, one of its
``files`` (so its sha256 and size are the card's), which holds the evaluations at full precision
(``ttompc.zoo.evaluations``). ``load_evaluations`` reads them into a parsed card from the file's bytes, checked
against the card; the registry (zoo cards) and the Hub download do so. Besides our record the rendered front matter
carries the Hub's keys: ``library_name: ttompc``, ``license``, ``tags``, ``datasets`` (Hub ids of the training data),
``base_model`` (the source of a fine-tuned model) and a ``model-index`` that
``huggingface_hub.ModelCard.load(...).data.eval_results`` reads: the headline results only, one per evaluation that
has them, rounded to their standard errors (``ttompc.zoo.rounding``). A card whose ``model-index`` states a number
its evaluations do not hold is refused once they are loaded.

Cards of the earlier formats held their numbers in the front matter (``evaluations: {name: {command, what,
metrics}}``, or the first format's ``metrics: {key: {value, how}}``); they load read-only (those published to the Hub
before, for instance), with their numbers from the front matter and their model-index checked at once. They are
never written: publishing the same bytes again writes the card in this layout, its numbers moved to a metrics file.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from ttompc.model_slots import FINE_TUNED, MODEL_SLOTS
from ttompc.zoo.errors import CardError
from ttompc.zoo.evaluations import (
    decode_evaluations,
    evaluations_from_metrics,
    headline_metrics,
    index_mismatches,
    validate_evaluations,
)
from ttompc.zoo.rounding import rounded

KINDS = tuple(MODEL_SLOTS)  # a card's kind is the model slot its model fills (pre-trained or DAgger fine-tuned)
LIBRARY_NAME = "ttompc"
INFERENCE_KEYS = ("rtg_scale", "conditioning")  # what the card's ``inference`` section may hold
REQUIRED_FILES = ("model.safetensors", "config.json")
# Names become directory and file names in the cache: one path component, no leading dot, no "..".
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")
_SHA256_RE = re.compile(r"^[0-9a-f]{64}$")
_OPTIONAL_KEYS = ("datasets", "base_model", "inference", "evaluations")  # left out of the front matter when empty
_HUB_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,95}/[A-Za-z0-9][A-Za-z0-9._-]{0,95}$")
_FRONT_MATTER_RE = re.compile(r"\A---[ \t]*\r?\n(.*?)\r?\n---[ \t]*(?:\r?\n|\Z)(.*)\Z", re.DOTALL)
_REPUBLISH = "publish the same bytes again (`ttompc zoo publish`) to write the card with its metrics file"


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
    """The front matter of ``zoo/<name>.md`` (``body`` is the Markdown after it).

    ``evaluations_file`` names the entry of ``files`` that holds the evaluations (``""``: none, or an earlier format's
    card whose numbers are in its front matter). ``evaluations`` are the numbers once read: from that file through
    ``load_evaluations``, or from an earlier format's front matter. ``stated_index`` keeps the (metric key, value)
    pairs of the parsed ``model-index`` until ``load_evaluations`` checks them."""

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
    evaluations_file: str = ""
    stated_index: list[tuple[Any, Any]] = field(default_factory=list, compare=False, repr=False)

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
        if self.evaluations_file and (self.evaluations_file not in names or self.evaluations_file in REQUIRED_FILES):
            raise CardError(
                f"card {self.name!r}: evaluations must name its metrics file, one of its files besides "
                f"{REQUIRED_FILES}, got {self.evaluations_file!r}"
            )
        bad = [d for d in self.datasets if not _HUB_ID_RE.fullmatch(d) or ".." in d]
        if bad:
            raise CardError(f"card {self.name!r}: datasets must be Hugging Face ids ORG/NAME, got {bad}")
        if self.base_model and (self.kind != FINE_TUNED or not _HUB_ID_RE.fullmatch(self.base_model)):
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

    @property
    def evaluations_entry(self) -> FileEntry | None:
        """The entry of ``files`` that holds the evaluations; None for a card without one."""
        return next((f for f in self.files if f.filename == self.evaluations_file), None)

    def to_dict(self) -> dict[str, Any]:
        """Front-matter mapping (also one entry of ``index.json``); key order is the documented card order.
        ``evaluations`` is the metrics file's name (an earlier format's card: its numbers, as it states them)."""
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
            "evaluations": self.evaluations_file or self.evaluations,
        }

    def front_matter(self) -> dict[str, Any]:
        """The record (``to_dict``) plus the Hub's derived keys; empty optional keys are left out."""
        record = {k: v for k, v in self.to_dict().items() if v or k not in _OPTIONAL_KEYS}
        index = self.model_index()
        return {"library_name": LIBRARY_NAME, **record, **({"model-index": index} if index else {})}

    def model_index(self) -> list[dict[str, Any]]:
        """The Hub's ``model-index``: one result per evaluation with a headline (``headline_metrics``), its dataset's
        ``config`` naming the evaluation, each value rounded to its standard error; empty when no evaluation has one.
        The other numbers and the commands stay in the metrics file (the Hub's result format has no place for a
        command)."""
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
            metrics = [
                {"name": label, "type": key, "value": rounded(evaluation["metrics"], key)} for key, label in keys
            ]
            results.append({"task": dict(task), "dataset": dataset, "metrics": metrics})
        return [{"name": self.name, "results": results}] if results else []

    @classmethod
    def from_dict(cls, d: dict[str, Any], body: str = "") -> ModelCard:
        """The card of the front matter ``d`` (any format), checked; ``CardError`` names what is wrong. Numbers in
        the front matter (an earlier format) are read and the model-index checked against them; a card with a
        metrics file keeps its model-index in ``stated_index`` for ``load_evaluations``."""
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
        evaluations = d.get("evaluations") or {}
        evaluations_file = evaluations if isinstance(evaluations, str) else ""
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
            evaluations={} if evaluations_file else evaluations,
            license=str(d.get("license", "mit")),
            tags=[str(t) for t in d.get("tags") or []],
            datasets=[str(t) for t in d.get("datasets") or []],
            base_model=str(d.get("base_model") or ""),
            inference=d.get("inference") or {},
            body=body,
            evaluations_file=evaluations_file,
            stated_index=_model_index_values(d["model-index"]) if "model-index" in d else [],
        )
        if not evaluations_file:
            _check_model_index(card)
        return card


def load_evaluations(card: ModelCard, data: bytes) -> ModelCard:
    """``card`` with its evaluations read from ``data``, the bytes of its metrics file (``evaluations_entry``):
    ``CardError`` when they are not the bytes the card lists (sha256 and size), not a metrics file, or do not hold
    the numbers its model-index states."""
    entry = card.evaluations_entry
    if entry is None:
        raise CardError(f"card {card.name!r} names no metrics file")
    actual = hashlib.sha256(data).hexdigest()
    if (actual, len(data)) != (entry.sha256, entry.size):
        raise CardError(
            f"card {card.name!r}: {entry.filename} is not the file the card lists (sha256 {actual}, {len(data)} "
            f"bytes; the card: {entry.sha256}, {entry.size} bytes)",
            "a card's numbers change only by publishing them (`ttompc zoo publish --card-metrics`)",
        )
    card.evaluations = decode_evaluations(data, f"card {card.name!r}: {entry.filename}")
    _check_model_index(card)
    return card


def _check_model_index(card: ModelCard) -> None:
    """``CardError`` unless every number of the card's stated model-index is one of its evaluations' metrics (as
    measured, or rounded to its standard error)."""
    wrong = index_mismatches(card.stated_index, card.evaluations)
    if wrong:
        raise CardError(
            f"card {card.name!r}: model-index does not match the evaluations' metrics ({', '.join(wrong)})",
            "edit the metrics file only and publish the card again (the model-index is derived from it)",
        )


def _model_index_values(index: Any) -> list[tuple[Any, Any]]:
    """(type, value) of every metric of a Hub ``model-index``; ``CardError`` when it does not have that shape."""
    try:
        return [(m["type"], m["value"]) for entry in index for r in entry["results"] for m in r["metrics"]]
    except (TypeError, KeyError):
        raise CardError(
            "model-index must be a Hub model-index: [{name, results: [{task, dataset, metrics}]}]"
        ) from None


def _from_first_format(d: dict[str, Any]) -> dict[str, Any]:
    """A front matter of the first card format (``metrics: {key: {value, how}}``, ``headline_metrics``,
    ``inference.protocol``: the commands again) with its numbers as front-matter evaluations, so cards published
    before the change (on the Hub, in a user's zoo) still load; any other front matter as given."""
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
    """The card in ``text``, its front matter checked; a card with a metrics file has its evaluations once
    ``load_evaluations`` has read that file."""
    match = _FRONT_MATTER_RE.match(text)
    if match is None:
        raise CardError("a model card must start with a YAML front matter block between '---' lines")
    try:
        front = yaml.safe_load(match.group(1))
    except yaml.YAMLError as err:
        raise CardError(f"card front matter is not valid YAML: {err}") from None
    return ModelCard.from_dict(front, body=match.group(2))


def render_card(card: ModelCard) -> str:
    """The card file: its front matter, with mappings and lists of plain values in flow style (``{...}``, ``[...]``),
    then its body. Only a card whose numbers are in its metrics file is written: ``CardError`` for one whose numbers
    are in its front matter (an earlier format) or whose metrics file has not been read (``load_evaluations``)."""
    if card.evaluations and not card.evaluations_file:
        raise CardError(f"card {card.name!r} holds its numbers in its front matter (an earlier format)", _REPUBLISH)
    if card.evaluations_file and not card.evaluations:
        raise CardError(f"card {card.name!r}: its {card.evaluations_file} has not been read (load_evaluations)")
    front = yaml.safe_dump(card.front_matter(), sort_keys=False, allow_unicode=True, default_flow_style=None, width=110)
    return f"---\n{front}---\n{card.body}"


def read_card(path: Path) -> ModelCard:
    """Parse ``path`` and check that the card's name matches its file name (``zoo/<name>.md``); its evaluations are
    not read (``ttompc.zoo.registry.load_card`` reads them too)."""
    try:
        card = parse_card(path.read_text(encoding="utf-8"))
    except CardError as err:
        raise CardError(f"{path}: {err}") from None
    if card.name != path.stem:
        raise CardError(f"{path}: card name {card.name!r} must match the file name {path.stem!r}")
    return card
