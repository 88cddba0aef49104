"""Publishing a model bundle: hash its two files, write its evaluations to a metrics file beside them, write the card,
and put them where users fetch them: a local directory plus the zoo's card and index (``publish``), or a Hugging
Face Hub repository with the card as its ``README.md`` in one commit (``publish_to_hub``). Datasets made by
``ttompc generate`` go to a Hub dataset repository the same way (``publish_dataset``).

The zoo stores bundles and never builds a model (``ttompc.policy`` imports the zoo to load names, not the reverse):
a Lightning checkpoint is converted by the caller (``ttompc zoo publish`` does). Published are ``model.safetensors``
and ``config.json`` of the bundle and the card's ``metrics.json`` (the evaluations at full precision; none for a card
without evaluations), each listed in the card with its sha256 and size. Card fields come from the bundle's
``config.json`` (``scenario: {name, version}``, ``model`` = architecture, optionally ``kind``, ``recipe``,
``data_card``, ``code_version``, and ``extra``: ``rtg_scale`` for the inference settings, ``finetuned_from`` for
``base_model``) over an existing card's hand-edited fields (body, licence, tags, recipe, ...), and explicit
``card_fields`` over both.

A local destination is claimed (``claim_destination``): new, empty, or a folder of published bundle files alone
(``model.safetensors``, ``config.json``, ``metrics.json``: republishing refreshes them); a folder holding anything
else is refused before any work, nothing in it overwritten.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import urllib.parse
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ttompc.model_slots import FINE_TUNED, MODEL_SLOTS, PRETRAINED, slot_flag, slot_of
from ttompc.outputs import claim_folder
from ttompc.version import code_version
from ttompc.zoo.cache import check_bundle, inside, sha256_file
from ttompc.zoo.cards import REQUIRED_FILES, FileEntry, ModelCard, read_card, render_card, validate_name
from ttompc.zoo.download import local_path
from ttompc.zoo.errors import DownloadError, PublishError
from ttompc.zoo.evaluations import METRICS_FILE, encode_evaluations, validate_evaluations
from ttompc.zoo.hub import CARD_FILE, HubRef, is_hub_ref, parse_hf_url, upload
from ttompc.zoo.registry import read_evaluations, write_index, zoo_path

DEFAULT_TAGS = ("ttompc", "trajectory-optimization", "mpc")
MANIFEST_FILE = "manifest.json"  # a dataset folder's file list with sha256 (``ttompc.data.generate``)
Evaluate = Callable[[Path], dict[str, dict[str, Any]]]  # bundle dir -> the card's evaluations


def publish(
    source: str | Path,
    name: str,
    to: str,
    *,
    zoo_dir: str | Path | None = None,
    metrics: dict[str, dict[str, Any]] | None = None,
    skip_eval: bool = False,
    evaluate: Evaluate | None = None,
    base_url: str | None = None,
    card_fields: dict[str, Any] | None = None,
) -> ModelCard:
    """Publish the bundle dir ``source`` as ``name`` into ``to``: its two files and the card's metrics file
    (``metrics.json``, removed from ``to`` when the card has no evaluations); returns the new card.

    ``to`` is a local directory or ``file://`` URL. Card URLs are relative when ``to`` lies inside the zoo dir
    (models shipped with the repository), ``base_url + filename`` when the files will be uploaded there by hand,
    else ``file://``. Metrics: see ``_card``.
    """
    validate_name(name)
    zoo = zoo_path(zoo_dir)
    dest = claim_destination(to)
    card_path = zoo / f"{name}.md"
    bundle = _bundle_dir(Path(source))
    config = check_bundle(bundle)
    files = [
        FileEntry(f, _url_for(dest / f, zoo, base_url), sha256_file(bundle / f), (bundle / f).stat().st_size)
        for f in REQUIRED_FILES
    ]
    card = _card(bundle, config, name, files, card_path, metrics, skip_eval, evaluate, card_fields, name)
    evaluations = _add_metrics_file(card, _url_for(dest / METRICS_FILE, zoo, base_url))
    dest.mkdir(parents=True, exist_ok=True)
    for entry in files:
        if _copy_hashed(bundle / entry.filename, dest / entry.filename) != (entry.sha256, entry.size):
            raise PublishError(f"{bundle / entry.filename} changed while it was being published; publish again")
    if evaluations is None:
        (dest / METRICS_FILE).unlink(missing_ok=True)  # a previous card's numbers, not this one's
    else:
        staged = dest / f".{METRICS_FILE}.tmp"
        staged.write_bytes(evaluations)
        os.replace(staged, dest / METRICS_FILE)
    zoo.mkdir(parents=True, exist_ok=True)
    tmp = card_path.with_name(f".{card_path.name}.tmp")
    tmp.write_text(render_card(card), encoding="utf-8")
    os.replace(tmp, card_path)
    write_index(zoo)
    return card


def publish_to_hub(
    source: str | Path,
    to: str,
    *,
    name: str | None = None,
    private: bool = False,
    zoo_dir: str | Path | None = None,
    metrics: dict[str, dict[str, Any]] | None = None,
    skip_eval: bool = False,
    evaluate: Evaluate | None = None,
    card_fields: dict[str, Any] | None = None,
) -> tuple[ModelCard, str]:
    """Publish the bundle dir ``source`` to the Hub model repository ``to`` (``hf://ORG/NAME[@BRANCH]``): its two
    files, the card's metrics file and the card as ``README.md``, in one commit; returns the card and the commit id.

    The card is named ``name`` (default: the repository's NAME) and lists the files by name (the repository's top
    level); a zoo card of that name supplies the hand-edited fields as for ``publish``. Nothing is written locally.
    """
    ref = parse_hf_url(to)
    if ref.repo_type != "model":
        raise PublishError(f"{to}: a model bundle goes to a model repository (hf://ORG/NAME), not a dataset one")
    name = validate_name(name or ref.repo_id.split("/")[1])
    bundle = _bundle_dir(Path(source))
    config = check_bundle(bundle)
    files = [FileEntry(f, f, sha256_file(bundle / f), (bundle / f).stat().st_size) for f in REQUIRED_FILES]
    card_path = zoo_path(zoo_dir) / f"{name}.md"
    load_as = str(HubRef(ref.repo_id))
    card = _card(bundle, config, name, files, card_path, metrics, skip_eval, evaluate, card_fields, load_as)
    evaluations = _add_metrics_file(card, METRICS_FILE)
    with tempfile.TemporaryDirectory(prefix="ttompc-card-") as tmp:
        readme = Path(tmp) / CARD_FILE
        readme.write_text(render_card(card), encoding="utf-8")
        uploads = {**{f: bundle / f for f in REQUIRED_FILES}, CARD_FILE: readme}
        if evaluations is not None:
            uploads[METRICS_FILE] = Path(tmp) / METRICS_FILE
            uploads[METRICS_FILE].write_bytes(evaluations)
        commit = upload(ref, uploads, f"Publish {name} ({card.kind}, {card.scenario})", private=private)
    return card, commit


def publish_dataset(folder: str | Path, to: str, *, private: bool = False) -> str:
    """Publish a dataset folder written by ``ttompc generate`` to the Hub dataset repository ``to``
    (``hf://datasets/ORG/NAME[@BRANCH]``) in one commit: its card (``README.md``, whose ``configs:`` section lets
    ``datasets.load_dataset`` find the splits), ``manifest.json`` and every parquet shard the manifest lists, each
    checked against the manifest's sha256 first; returns the commit id."""
    ref = parse_hf_url(to)
    if ref.repo_type != "dataset":
        raise PublishError(f"{to}: a dataset goes to a dataset repository, hf://datasets/ORG/NAME")
    root = Path(folder)
    missing = [f for f in (CARD_FILE, MANIFEST_FILE) if not (root / f).is_file()]
    if missing:
        raise PublishError(f"{root} is not a dataset folder of `ttompc generate`: missing {missing}")
    manifest = json.loads((root / MANIFEST_FILE).read_text(encoding="utf-8"))
    uploads = {CARD_FILE: root / CARD_FILE, MANIFEST_FILE: root / MANIFEST_FILE}
    for shard in manifest.get("shards", []):
        for entry in shard["files"]:
            path = inside(root, *Path(entry["path"]).parts)
            if not path.is_file() or sha256_file(path) != entry["sha256"]:
                raise PublishError(
                    f"{path} is missing or does not match manifest.json",
                    "re-run `ttompc generate` with the same arguments to repair the folder",
                )
            uploads[Path(entry["path"]).as_posix()] = path
    return upload(ref, uploads, f"Publish dataset {manifest.get('name', root.name)}", private=private)


def _card(
    bundle: Path,
    config: dict[str, Any],
    name: str,
    files: list[FileEntry],
    card_path: Path,
    metrics: dict[str, dict[str, Any]] | None,
    skip_eval: bool,
    evaluate: Evaluate | None,
    card_fields: dict[str, Any] | None,
    load_as: str,
) -> ModelCard:
    """The card of ``bundle`` published as ``files``. Its evaluations (``metrics``, ``{name: {command, what,
    metrics}}``): none with ``skip_eval``; when the files are byte-identical to the ones the existing card describes
    (its numbers were measured on these bytes), the card's, with those of ``metrics`` replacing the evaluations of the
    same name or with a metric in common; else ``metrics``, or ``evaluate(bundle)`` (the standard evaluation hook)
    when not given. A card never silently claims metrics it was not given."""
    previous = read_card(card_path) if card_path.is_file() else None
    same_files = previous is not None and {
        (f.filename, f.sha256) for f in previous.files if f.filename in REQUIRED_FILES
    } == {(f.filename, f.sha256) for f in files}
    if metrics is None and not skip_eval and not same_files:
        if evaluate is None:
            raise PublishError(f"no metrics for the card of {name}", _metrics_hint(config, card_fields))
        metrics = evaluate(bundle)
    evaluations = validate_evaluations(metrics or {})
    if previous is not None and same_files and not skip_eval:  # measured on these bytes: read from its metrics file
        evaluations = _updated(read_evaluations(previous, card_path.parent).evaluations, evaluations)
    fields: dict[str, Any] = {"name": name, "kind": PRETRAINED, "license": "mit", "tags": list(DEFAULT_TAGS)}
    if previous is not None:  # keep what a maintainer edited by hand; evaluations and files are replaced
        fields.update(
            kind=previous.kind,
            license=previous.license,
            tags=previous.tags,
            recipe=previous.recipe,
            data_card=previous.data_card,
            datasets=previous.datasets,
            base_model=previous.base_model,
        )
    fields.update({k: v for k, v in _from_config(config).items() if v})
    fields.update(evaluations=evaluations, files=[f.to_dict() for f in files], **(card_fields or {}))
    fields["inference"] = inference_settings(config)
    card = ModelCard.from_dict(fields, body=previous.body if previous else "")
    card.body = card.body or _default_body(card, load_as)
    return card


def _add_metrics_file(card: ModelCard, url: str) -> bytes | None:
    """Add the card's metrics file (``METRICS_FILE``: its evaluations, fetched from ``url``) to its files and name
    it in the card; returns the file's bytes, None for a card without evaluations (it has no metrics file)."""
    if not card.evaluations:
        return None
    data = encode_evaluations(card.evaluations)
    card.files.append(FileEntry(METRICS_FILE, url, hashlib.sha256(data).hexdigest(), len(data)))
    card.evaluations_file = METRICS_FILE
    return data


def _updated(evaluations: dict[str, dict[str, Any]], new: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """``evaluations`` less the ones ``new`` supersedes (of the same name, or with a metric in common), each of
    ``new`` in the place of its namesake, else after them."""
    keys = {k for e in new.values() for k in e["metrics"]}
    out = {n: new.get(n, e) for n, e in evaluations.items() if n in new or not keys & set(e["metrics"])}
    out.update(new)
    return out


def _metrics_hint(config: dict[str, Any], card_fields: dict[str, Any] | None) -> str:
    """How to make the card metrics of the bundle with ``config``: evaluate it (as ``--ft-model`` when it is
    fine-tuned), turn the two reports into card metrics with ``ttompc zoo metrics`` and publish with them."""
    kind = (card_fields or {}).get("kind") or _from_config(config)["kind"] or PRETRAINED
    flag = slot_flag(kind if kind in MODEL_SLOTS else PRETRAINED)
    return (
        f"make them with `ttompc evaluate warmstart {flag} MODEL --out eval/ws` and `ttompc evaluate mpc {flag} MODEL "
        f"--out eval/mpc` (MODEL: the bundle folder or .ckpt you publish), then `ttompc zoo metrics --method {kind} "
        "--warmstart eval/ws/warmstart.json --mpc eval/mpc/mpc.json --out metrics.json`, and publish with "
        "--card-metrics metrics.json (metrics=... in Python), or with --skip-eval (skip_eval=True) for a card without "
        "metrics"
    )


def inference_settings(config: dict[str, Any]) -> dict[str, Any]:
    """The card's ``inference`` section: the conditioning the model plans with by default (``rtg_scale`` from the
    bundle's ``extra``, else the paper's 1; a model with a value output feeds its value under
    ``protocol=recommended``). The commands its numbers were measured with are the evaluations'."""
    extra = _extra(config)
    conditioning = "rtg_0 = -rtg_scale * J_REL (cost of the relaxed problem), ctg_0 = 0"
    if int((config.get("model") or {}).get("value_width", 0) or 0) > 0:
        conditioning = (
            "rtg_t = -V(x_t, t), the model's value output at the measured state (protocol=recommended, "
            f"rtg_mode=value); under the paper's ledger {conditioning}"
        )
    return {"rtg_scale": float(extra.get("rtg_scale", 1.0)), "conditioning": conditioning}


def _extra(config: dict[str, Any]) -> dict[str, Any]:
    """The bundle's free-form metadata (``Planner.extra``), ``{}`` when absent or not a mapping."""
    extra = config.get("extra")
    return extra if isinstance(extra, dict) else {}


def _from_config(config: dict[str, Any]) -> dict[str, Any]:
    scenario, model = config.get("scenario"), config.get("model")
    if not isinstance(scenario, dict) or not {"name", "version"} <= set(scenario) or not isinstance(model, dict):
        raise PublishError(
            "the bundle's config.json needs 'scenario': {'name', 'version'} and 'model' (the "
            "architecture config) to fill the card"
        )
    extra = _extra(config)
    slot = slot_of(extra)
    return {
        "kind": config.get("kind") or (slot if slot == FINE_TUNED else None),  # else the earlier card's, or TTO
        "scenario": {"name": scenario["name"], "version": scenario["version"]},
        "architecture": model,
        # Planner bundles store the recipe's content; the card wants its path (pass it via card_fields).
        "recipe": config["recipe"] if isinstance(config.get("recipe"), str) else "",
        "data_card": config.get("data_card"),
        "code_version": str(config.get("code_version") or code_version()),
        "base_model": _base_model(extra.get("finetuned_from")),
    }


def _base_model(source: object) -> str:
    """The source a fine-tuned bundle records (``extra.finetuned_from``) as the Hub's ``base_model`` when it is a
    Hub repository (ORG/NAME); a zoo name, a local folder or a checkpoint is no Hub model and gives ""."""
    if not is_hub_ref(source):
        return ""
    try:
        return parse_hf_url(str(source)).repo_id
    except DownloadError:
        return ""


def _bundle_dir(source: Path) -> Path:
    if source.is_dir():
        return source
    if source.is_file() and source.suffix == ".ckpt":
        raise PublishError(
            f"{source} is a Lightning checkpoint, not a bundle directory",
            "convert it with Planner.from_pretrained(CKPT).save(DIR), or publish it with `ttompc zoo publish`",
        )
    raise PublishError(f"{source} is neither a bundle directory nor a Lightning .ckpt file")


def claim_destination(to: str) -> Path:
    """The local folder ``to`` (a path or ``file://`` URL) that ``publish`` writes, claimed for it (module doc);
    raises ``PublishError`` for a remote URL and ``UserError`` for a folder of other files or one not writable."""
    dest = _destination(to)
    published = {*REQUIRED_FILES, METRICS_FILE}
    staged = {f".{name}.tmp" for name in published}  # left by an interrupted publish (``_copy_hashed``)
    claim_folder(dest, "zoo publish", lambda folder: all(p.name in published | staged for p in folder.iterdir()))
    return dest


def _destination(to: str) -> Path:
    scheme = urllib.parse.urlsplit(to).scheme
    if scheme == "file":
        return local_path(to, None)
    if scheme and not Path(to).is_absolute():
        raise PublishError(
            f"cannot publish to {to!r}: write to a local directory or file:// URL, upload the files "
            "yourself and pass base_url (--base-url) so the card points at them"
        )
    return Path(to)


def _copy_hashed(src: Path, dst: Path) -> tuple[str, int]:
    """Copy through a temporary file (so ``dst`` is never half-written) while hashing what is written."""
    digest, size = hashlib.sha256(), 0
    tmp = dst.with_name(f".{dst.name}.tmp")
    with open(src, "rb") as fin, open(tmp, "wb") as fout:
        for chunk in iter(lambda: fin.read(1 << 20), b""):
            fout.write(chunk)
            digest.update(chunk)
            size += len(chunk)
    os.replace(tmp, dst)
    return digest.hexdigest(), size


def _url_for(path: Path, zoo: Path, base_url: str | None) -> str:
    if base_url:
        return f"{base_url.rstrip('/')}/{path.name}"
    resolved, zoo_resolved = path.resolve(), zoo.resolve()
    if resolved.is_relative_to(zoo_resolved):
        return resolved.relative_to(zoo_resolved).as_posix()
    return resolved.as_uri()


def _default_body(card: ModelCard, load_as: str) -> str:
    """The body of a new card: what the model is and how to load it (``load_as``: its zoo name or Hub URL); a zoo
    card links the zoo's README, which lies beside it."""
    where = "the ttompc model zoo's README" if is_hub_ref(load_as) else "[README.md](README.md)"
    return (
        f"\n# {card.name}\n\n"
        f"{card.kind} model for the `{card.scenario}` scenario (version {card.scenario_version}).\n\n"
        "```python\nfrom ttompc.policy import Planner\n\n"
        f'planner = Planner.from_pretrained("{load_as}")\n```\n\n'
        f"Card format, metric definitions and download details: {where}.\n"
    )
