"""The Hugging Face Hub: ``hf://`` references, verified downloads through the Hugging Face cache and publishing in
one commit, with the installed ``huggingface_hub`` client (imported only when a Hub reference is used).

References: ``hf://ORG/NAME[@REVISION]`` (a model repository), ``hf://datasets/ORG/NAME[@REVISION]`` (a dataset
repository), and for single files in card URLs ``hf://ORG/NAME[@REVISION]/path/in/repo``. The endpoint, token,
cache and offline mode are the client's own settings (``HF_ENDPOINT``, ``HF_TOKEN`` or ``hf auth login``,
``HF_HOME``/``HF_HUB_CACHE``, ``HF_HUB_OFFLINE``). Every failure of the client becomes one ``DownloadError`` or
``PublishError`` line naming the reference.

A model repository holds a bundle and the card's metrics file at its top level plus the model card as
``README.md``; ``download_model`` reads the card at the requested revision, fetches each file the card lists at that
same commit and checks it against the card's sha256 and size before anyone reads it. A file that does not match is
removed from the Hugging Face cache (blob and snapshot link), so a later run downloads it again instead of trusting
it.
"""

from __future__ import annotations

import contextlib
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from ttompc.zoo.cache import check_bundle, sha256_file
from ttompc.zoo.cards import CardError, ModelCard, load_evaluations, parse_card
from ttompc.zoo.errors import ChecksumError, DownloadError, PublishError

SCHEME = "hf://"
CARD_FILE = "README.md"  # the model or dataset card in a Hub repository
_PART_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,95}$")
_REVISION_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,199}$")
_FORMS = "hf://ORG/NAME[@REVISION] (a dataset: hf://datasets/ORG/NAME[@REVISION])"


@dataclass(frozen=True)
class HubRef:
    """A Hub repository at an optional revision, and optionally one file in it."""

    repo_id: str  # ORG/NAME
    repo_type: str = "model"  # "model" or "dataset"
    revision: str | None = None  # None: the default branch
    path: str = ""  # a file in the repository ("" for the repository itself)

    def __str__(self) -> str:
        prefix = "datasets/" if self.repo_type == "dataset" else ""
        revision = f"@{self.revision}" if self.revision else ""
        return f"{SCHEME}{prefix}{self.repo_id}{revision}" + (f"/{self.path}" if self.path else "")


def is_hub_ref(source: object) -> bool:
    return isinstance(source, str) and source.startswith(SCHEME)


def parse_hf_url(url: str, *, with_path: bool = False) -> HubRef:
    """``url`` as a ``HubRef``; ``with_path``: a file URL (``.../path/in/repo`` required), else a repository."""
    parts = url.removeprefix(SCHEME).split("/") if url.startswith(SCHEME) else []
    repo_type = "dataset" if parts[:1] == ["datasets"] else "model"
    parts = parts[1:] if repo_type == "dataset" else parts
    name, _, revision = parts[1].partition("@") if len(parts) > 1 else ("", "", "")
    path = "/".join(parts[2:])
    ok = (
        len(parts) >= 2
        and _PART_RE.fullmatch(parts[0])
        and _PART_RE.fullmatch(name)
        and (not revision or _REVISION_RE.fullmatch(revision))
        and ".." not in parts[0] + name + revision
        and (bool(path) == with_path)
        and not any(p in ("", ".", "..") for p in parts[2:])
    )
    if not ok:
        expected = "hf://org/repo[@revision]/path/in/repo" if with_path else _FORMS
        raise DownloadError(f"{url!r}: expected {expected}")
    return HubRef(f"{parts[0]}/{name}", repo_type, revision or None, path)


def _client() -> Any:
    """The ``huggingface_hub`` package with the submodules used here imported (they are not loaded lazily)."""
    try:
        import huggingface_hub
        import huggingface_hub.constants
        import huggingface_hub.errors
        import huggingface_hub.utils
    except ImportError:
        raise DownloadError(f"{SCHEME} URLs need huggingface_hub (pip install huggingface_hub)") from None
    return huggingface_hub


def hub_file(ref: HubRef, filename: str, progress: bool = True) -> Path:
    """The local path of ``filename`` of ``ref`` in the Hugging Face cache, downloaded if needed (and allowed)."""
    hf = _client()
    try:
        with _progress_bars(hf, progress):
            return Path(hf.hf_hub_download(ref.repo_id, filename, repo_type=ref.repo_type, revision=ref.revision))
    except Exception as err:  # the client raises many unrelated types: each becomes one line naming the reference
        raise DownloadError(_describe(hf, err, ref, filename)) from err


def _describe(hf: Any, err: Exception, ref: HubRef, filename: str) -> str:
    errors = hf.errors
    where = f"{ref}: {filename}"
    if isinstance(err, errors.LocalEntryNotFoundError):
        if hf.constants.HF_HUB_OFFLINE:
            return (
                f"{where} is not in the Hugging Face cache ({hf.constants.HF_HUB_CACHE}) and HF_HUB_OFFLINE=1 "
                "forbids downloading it; run once with network access"
            )
        return f"{where} is not in the Hugging Face cache and {hf.constants.ENDPOINT} could not be reached"
    if isinstance(err, errors.RevisionNotFoundError):
        return f"{ref}: no revision {ref.revision!r} in {ref.repo_type} repository {ref.repo_id}"
    if isinstance(err, errors.RepositoryNotFoundError):
        return (
            f"{ref}: no {ref.repo_type} repository {ref.repo_id} on {hf.constants.ENDPOINT} "
            "(or it is private and no token that can read it is set: HF_TOKEN or `hf auth login`)"
        )
    if isinstance(err, errors.RemoteEntryNotFoundError):
        return f"{where} does not exist in the repository"
    return f"{where}: {type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"


@contextlib.contextmanager
def _progress_bars(hf: Any, progress: bool) -> Iterator[None]:
    """The client's progress bars off for the call when ``progress`` is false (restored afterwards)."""
    utils = hf.utils
    if progress or utils.are_progress_bars_disabled():
        yield
        return
    utils.disable_progress_bars()
    try:
        yield
    finally:
        utils.enable_progress_bars()


def download_model(url: str, progress: bool = True) -> tuple[Path, dict[str, Any]]:
    """The bundle dir of the model repository ``url`` (``hf://ORG/NAME[@REVISION]``) in the Hugging Face cache and
    its parsed ``config.json``; every file the card lists is fetched at the card's commit and verified against its
    sha256 and size, the card's model-index checked against its metrics file (a card of an earlier format, with its
    numbers in the front matter, against those), then the bundle is checked like a local one (``check_bundle``)
    before anyone loads it.

    Raises ``DownloadError`` (unknown repository, revision or file, offline without a cached copy), ``CardError``
    (a README.md that is no ttompc card), ``ChecksumError`` (bytes that are not the card's; they are removed) or
    ``BundleError``."""
    ref = parse_hf_url(url)
    if ref.repo_type != "model":
        raise DownloadError(f"{url}: a model is loaded from a model repository, not a dataset")
    card_path = hub_file(ref, CARD_FILE, progress)
    card = _read_card(card_path, ref)
    pinned = replace(ref, revision=card_path.parent.name)  # snapshots/<commit>/README.md: the files of that commit
    for entry in card.files:
        if entry.url != entry.filename:
            raise DownloadError(
                f"{url}: the card lists {entry.filename} at {entry.url!r}; a Hub model keeps its files at the top "
                "level of the repository (url = file name)"
            )
        verify(hub_file(pinned, entry.filename, progress), entry.sha256, entry.size, f"{ref}: {entry.filename}")
    snapshot = card_path.parent
    if card.evaluations_file:  # its model-index must be its metrics file's numbers
        try:
            load_evaluations(card, (snapshot / card.evaluations_file).read_bytes())
        except CardError as err:
            raise CardError(f"{ref}: {err}") from None
    return snapshot, check_bundle(snapshot, within=snapshot.parents[1])  # <repo folder>/snapshots/<commit>


def _read_card(path: Path, ref: HubRef) -> ModelCard:
    try:
        return parse_card(path.read_text(encoding="utf-8"))
    except (CardError, UnicodeDecodeError) as err:
        raise CardError(f"{ref}: its {CARD_FILE} is not a ttompc model card ({err})") from None


def verify(path: Path, sha256: str, size: int, what: str) -> None:
    """Raise ``ChecksumError`` unless ``path`` holds ``size`` bytes with ``sha256``; a mismatching file is removed
    together with the cache blob it links to."""
    actual_size = path.stat().st_size
    actual = sha256_file(path) if actual_size == size else "-"
    if actual == sha256:
        return
    blob = path.resolve()
    with contextlib.suppress(FileNotFoundError):
        os.unlink(blob)
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)
    raise ChecksumError(
        f"{what}: sha256 mismatch, the card says {sha256} ({size} bytes), the download is {actual} "
        f"({actual_size} bytes); it was removed from the Hugging Face cache"
    )


def upload(ref: HubRef, files: dict[str, Path], message: str, *, private: bool) -> str:
    """Create the repository of ``ref`` if needed (``private`` then applies) and commit ``files`` (path in the
    repository -> local file) to its revision in one commit; returns the commit id.

    The token is the client's (``HF_TOKEN`` or ``hf auth login``); without one nothing is sent."""
    hf = _client()
    if hf.get_token() is None:
        raise PublishError(f"publishing to {ref} needs a Hugging Face token", "set HF_TOKEN or run `hf auth login`")
    api = hf.HfApi()
    operations = [hf.CommitOperationAdd(path_in_repo=p, path_or_fileobj=str(f)) for p, f in files.items()]
    try:
        api.create_repo(ref.repo_id, repo_type=ref.repo_type, private=private, exist_ok=True)
        info = api.create_commit(
            ref.repo_id, operations, commit_message=message, repo_type=ref.repo_type, revision=ref.revision
        )
    except Exception as err:  # HTTP, offline mode, invalid card metadata: one line naming the destination
        detail = str(err).splitlines()[0] if str(err) else ""
        raise PublishError(f"publishing to {ref} failed: {type(err).__name__}: {detail}") from err
    return str(info.oid)
