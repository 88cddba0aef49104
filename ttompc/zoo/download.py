"""Fetching published files into the cache: verified by sha256, resumable over HTTP, atomic.

Sources: a path relative to the card's directory (models shipped in the repository), ``file://``, ``http(s)://``
(``Range`` requests resume a ``.part`` file when the server supports them, otherwise the download restarts), and
``hf://org/repo[@revision]/path`` through huggingface_hub when it is installed. We use urllib rather than
``torch.hub.download_url_to_file`` because the latter cannot resume and would import torch for a file copy.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
import sys
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

from tqdm.auto import tqdm

from ttompc.progress import STDERR, progress_enabled
from ttompc.version import code_version
from ttompc.zoo.cache import assemble_bundle, blob_path, cache_root, inside, sha256_file
from ttompc.zoo.cards import FileEntry, ModelCard
from ttompc.zoo.errors import ChecksumError, DownloadError
from ttompc.zoo.hub import hub_file, parse_hf_url

try:
    import fcntl
except ImportError:  # Windows: no advisory locks, so concurrent downloads of one file are not coordinated
    fcntl = None  # type: ignore[assignment]

CHUNK = 1 << 20
TIMEOUT_S = 60.0
_CONTENT_RANGE_RE = re.compile(r"^bytes (\d+)-\d+/(?:\d+|\*)$")


def download_bundle(
    card: ModelCard, base_dir: Path, cache_dir: str | Path | None = None, progress: bool = True
) -> Path:
    """Fetch every file of ``card`` (relative URLs resolve against ``base_dir``) and return its bundle dir."""
    root = cache_root(cache_dir)
    for entry in card.files:
        fetch(entry, blob_path(root, entry.sha256), base_dir=base_dir, progress=progress)
    return assemble_bundle(root, card.name, card.files)


def read_published(entry: FileEntry, base_dir: Path) -> bytes:
    """The bytes of a small published file (a card's metrics file): read where it lies for a relative path (against
    ``base_dir``) or a ``file://`` URL, unchecked (the card checks them: ``load_evaluations``); from any other source
    fetched into the cache first (``fetch``: verified, and fetched once)."""
    if urllib.parse.urlsplit(entry.url).scheme.lower() in ("", "file"):
        path = local_path(entry.url, base_dir)
        try:
            return path.read_bytes()
        except OSError as err:
            raise DownloadError(f"cannot read {entry.url}: {err}") from None
    return fetch(entry, blob_path(cache_root(), entry.sha256), base_dir, progress=False).read_bytes()


def fetch(entry: FileEntry, dest: Path, base_dir: Path | None = None, progress: bool = True) -> Path:
    """Download ``entry`` to ``dest`` unless a copy with the published sha256 is already there; only verified
    bytes ever appear at ``dest``. A cached file whose bytes changed (same size or not) is downloaded again."""
    if _cached(entry, dest):
        return dest
    dest.parent.mkdir(parents=True, exist_ok=True)
    part = dest.with_name(dest.name + ".part")
    with _locked(dest.with_name(dest.name + ".lock")):
        if _cached(entry, dest):  # another process finished it while we waited for the lock
            return dest
        offset = part.stat().st_size if part.exists() else 0
        if offset >= entry.size:  # a stale or over-long partial cannot be resumed
            offset = 0
        stream, offset = _open(entry.url, offset, base_dir)
        digest = hashlib.sha256()
        with stream, open(part, "r+b" if offset else "w+b") as out:
            for chunk in iter(lambda: out.read(CHUNK), b""):  # re-hash the bytes we already have
                digest.update(chunk)
            with tqdm(
                total=entry.size,
                initial=offset,
                unit="B",
                unit_scale=True,
                unit_divisor=1024,
                desc=entry.filename,
                file=STDERR,
                disable=not (progress and progress_enabled()),  # also TTOMPC_PROGRESS / CI (ttompc.progress)
                leave=False,
            ) as bar:
                for chunk in iter(lambda: stream.read(CHUNK), b""):
                    out.write(chunk)
                    digest.update(chunk)
                    bar.update(len(chunk))
                    if out.tell() > entry.size:  # never let a wrong or hostile source fill the disk
                        break
            size = out.tell()
        actual = digest.hexdigest()
        if actual != entry.sha256 or size != entry.size:
            part.unlink()
            raise ChecksumError(
                f"{entry.filename} from {entry.url}: sha256 mismatch, expected {entry.sha256} ({entry.size} bytes), "
                f"got {actual} ({size} bytes); the downloaded file was deleted"
            )
        os.chmod(part, 0o444)  # blobs are shared by hard links: make accidental in-place edits fail
        os.replace(part, dest)
    return dest


def _cached(entry: FileEntry, dest: Path) -> bool:
    """Whether ``dest`` holds exactly the published bytes; a damaged copy is reported and removed.

    Re-hashing on every load is cheap for our bundles (a few MB, milliseconds) and catches edits in place that
    keep the size and modification time."""
    if not dest.is_file():
        return False
    if dest.stat().st_size == entry.size and sha256_file(dest) == entry.sha256:
        return True
    print(
        f"ttompc: cached {entry.filename} ({dest}) does not match its published sha256; downloading it again",
        file=sys.stderr,
    )
    os.chmod(dest, 0o644)
    dest.unlink()
    return False


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    """Serialise downloads of one blob across processes (e.g. DDP ranks all calling Planner.from_pretrained)."""
    if fcntl is None:
        yield
        return
    with open(path, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _open(url: str, offset: int, base_dir: Path | None) -> tuple[BinaryIO, int]:
    """A stream of ``url`` starting at ``offset`` if the source can resume, else at 0; returns the start used."""
    scheme = urllib.parse.urlsplit(url).scheme.lower()
    if scheme in ("http", "https"):
        return _open_http(url, offset)
    path = _hf_path(url) if scheme == "hf" else local_path(url, base_dir)
    try:
        fh = open(path, "rb")
    except OSError as err:
        raise DownloadError(f"cannot read {url}: {err}") from None
    fh.seek(offset)
    return fh, offset


def local_path(url: str, base_dir: Path | None) -> Path:
    """The file behind a ``file://`` URL or a relative path (which must stay inside ``base_dir``)."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme == "file":
        if parts.netloc not in ("", "localhost"):
            raise DownloadError(f"{url}: only local file:// URLs are supported")
        return Path(urllib.request.url2pathname(parts.path))
    if parts.scheme or Path(url).is_absolute():
        raise DownloadError(f"unsupported URL {url!r}: use a relative path, file://, http(s):// or hf://")
    if base_dir is None:
        raise DownloadError(f"relative URL {url!r} needs a base directory (the zoo dir holding the card)")
    return inside(base_dir, *Path(url).parts)


def _open_http(url: str, offset: int) -> tuple[BinaryIO, int]:
    headers = {"User-Agent": f"ttompc/{code_version()}"}
    if offset:
        headers["Range"] = f"bytes={offset}-"
    try:
        resp = urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=TIMEOUT_S)
    except urllib.error.HTTPError as err:
        err.close()
        if err.code == 416 and offset:  # our partial file does not fit the remote one: start over
            return _open_http(url, 0)
        raise DownloadError(f"{url}: HTTP {err.code} {err.reason}") from None
    except (urllib.error.URLError, OSError) as err:
        raise DownloadError(f"{url}: {getattr(err, 'reason', err)}") from None
    if not offset or resp.status != 206:
        return resp, 0  # a 200 answer to a Range request means the server ignored it: restart
    match = _CONTENT_RANGE_RE.match(resp.headers.get("Content-Range", ""))
    if match is None or int(match.group(1)) != offset:
        resp.close()
        return _open_http(url, 0)
    return resp, offset


def _hf_path(url: str) -> Path:
    """Resolve ``hf://org/repo[@revision]/path/in/repo`` to a local file via huggingface_hub's own cache."""
    ref = parse_hf_url(url, with_path=True)
    return hub_file(ref, ref.path)
