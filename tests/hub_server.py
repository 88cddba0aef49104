"""A Hugging Face Hub stand-in on the loopback for the real ``huggingface_hub`` client, in memory.

It implements exactly the endpoints that ttompc's use of the client (``huggingface_hub`` 2.x) and
``datasets.load_dataset("ORG/NAME")`` call:

    POST /api/repos/create                               create_repo (409 when it exists)
    POST /api/validate-yaml                              create_commit, when README.md is committed
    POST /api/{models|datasets}/ORG/NAME/preupload/REV   create_commit: upload mode per file (always "regular",
                                                         so the contents travel in the commit and no LFS or Xet
                                                         transfer endpoint is needed)
    POST /api/{models|datasets}/ORG/NAME/commit/REV      create_commit: the NDJSON commit (header + base64 files)
    HEAD|GET /[datasets/]ORG/NAME/resolve/REV/PATH       hf_hub_download: metadata headers, then the bytes
    GET /api/{models|datasets}/ORG/NAME/revision/REV     repo_info (datasets.load_dataset("ORG/NAME")): the commit
                                                         and its files
    GET /api/{models|datasets}/ORG/NAME/tree/REV[/PATH]  the file listing that load_dataset resolves the card's
                                                         ``configs:`` globs with (``?recursive=...`` honoured)
    GET /api/agent-harnesses                             the client's user-agent detection (at most once per
                                                         process and day): an empty registry

Errors carry the Hub's ``X-Error-Code`` header (``RepoNotFound``, ``RevisionNotFound``, ``EntryNotFound``), from
which the client raises its typed errors. Writes need ``Authorization: Bearer <a token in server.tokens>``; private
repositories are invisible without one. Any other request is answered 501 and recorded in ``server.unhandled``.
"""

from __future__ import annotations

import base64
import hashlib
import http.server
import json
import re
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import unquote, urlsplit

import yaml

_ID = r"(?P<repo>[A-Za-z0-9][\w.-]*/[A-Za-z0-9][\w.-]*)"
_API_RE = re.compile(rf"^/api/(?P<type>models|datasets)/{_ID}/(?P<action>preupload|commit)/(?P<rev>[^/]+)$")
_INFO_RE = re.compile(
    rf"^/api/(?P<type>models|datasets)/{_ID}/(?P<action>revision|tree)/(?P<rev>[^/]+)(?:/(?P<path>.*))?$"
)
_RESOLVE_RE = re.compile(rf"^/(?:(?P<type>datasets)/)?{_ID}/resolve/(?P<rev>[^/]+)/(?P<path>.+)$")


@dataclass
class Repo:
    private: bool
    branches: dict[str, str] = field(default_factory=dict)  # branch -> commit id
    commits: dict[str, dict[str, bytes]] = field(default_factory=dict)  # commit id -> {path: bytes}

    def commit(self, branch: str, files: dict[str, bytes], message: str) -> str:
        parent = self.branches.get(branch, "")
        tree = {**self.commits.get(parent, {}), **files}
        digest = hashlib.sha1(parent.encode() + message.encode())
        for path in sorted(tree):
            digest.update(path.encode() + b"\0" + hashlib.sha1(tree[path]).digest())
        oid = digest.hexdigest()
        self.commits[oid] = tree
        self.branches[branch] = oid
        return oid

    def resolve(self, revision: str) -> str | None:
        return self.branches.get(revision) or (revision if revision in self.commits else None)


class HubServer(http.server.ThreadingHTTPServer):
    daemon_threads = True

    def __init__(self, tokens: set[str]) -> None:
        super().__init__(("127.0.0.1", 0), _Handler)
        self.url = f"http://127.0.0.1:{self.server_address[1]}"
        self.tokens = tokens
        self.repos: dict[tuple[str, str], Repo] = {}  # (repo type, ORG/NAME) -> repository
        self.requests: list[tuple[str, str]] = []  # (method, path)
        self.unhandled: list[tuple[str, str]] = []
        self.lock = threading.Lock()

    def commits_posted(self) -> int:
        return sum(1 for method, path in self.requests if method == "POST" and "/commit/" in path)

    def tamper(self, repo_id: str, path: str, repo_type: str = "model") -> None:
        """Flip the last bytes of ``path`` in every commit of the repository: what a broken transfer or store
        would serve (same size, other bytes)."""
        for tree in self.repos[(repo_type, repo_id)].commits.values():
            if path in tree:
                tree[path] = tree[path][:-8] + bytes(b ^ 0xFF for b in tree[path][-8:])


class _Handler(http.server.BaseHTTPRequestHandler):
    server: HubServer

    def log_message(self, *args: Any) -> None:
        pass

    # ------------------------------------------------------------------------------------------------ helpers
    def _authorised(self) -> bool:
        header = self.headers.get("Authorization", "")
        return header.startswith("Bearer ") and header.removeprefix("Bearer ") in self.server.tokens

    def _send(self, status: int, body: bytes = b"", headers: dict[str, str] | None = None) -> None:
        self.send_response(status)
        for key, value in (headers or {}).items():
            self.send_header(key, value)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, status: int, payload: Any, error_code: str | None = None) -> None:
        headers = {"Content-Type": "application/json"}
        if error_code:
            headers |= {"X-Error-Code": error_code, "X-Error-Message": str(payload.get("error", ""))}
        self._send(status, json.dumps(payload).encode(), headers)

    def _body(self) -> bytes:
        return self.rfile.read(int(self.headers.get("Content-Length", 0)))

    def _repo(self, repo_type: str, repo_id: str) -> Repo | None:
        repo = self.server.repos.get((repo_type, repo_id))
        return None if repo is None or (repo.private and not self._authorised()) else repo

    def _unhandled(self) -> None:
        self.server.unhandled.append((self.command, self.path))
        self._json(501, {"error": f"{self.command} {self.path} is not implemented by the test hub"})

    # ------------------------------------------------------------------------------------------------ routes
    def do_POST(self) -> None:
        path = urlsplit(self.path).path
        self.server.requests.append(("POST", path))
        with self.server.lock:
            if path == "/api/validate-yaml":
                return self._validate_yaml()
            if path == "/api/repos/create":
                return self._create_repo()
            match = _API_RE.match(path)
            if match is None:
                return self._unhandled()
            if not self._authorised():
                return self._json(401, {"error": "Invalid credentials"}, "RepoNotFound")
            repo = self._repo(match["type"].removesuffix("s"), match["repo"])
            if repo is None:
                return self._json(404, {"error": "Repository not found"}, "RepoNotFound")
            body = self._body()
            if match["action"] == "preupload":
                files = json.loads(body)["files"]
                modes = [{"path": f["path"], "uploadMode": "regular", "shouldIgnore": False} for f in files]
                return self._json(200, {"files": modes})
            return self._commit(repo, match["type"], match["repo"], unquote(match["rev"]), body)

    def _validate_yaml(self) -> None:
        content = json.loads(self._body())["content"]
        front = content.split("---\n")[1] if content.startswith("---\n") else ""
        try:
            yaml.safe_load(front)
        except yaml.YAMLError as err:
            return self._json(400, {"errors": [{"message": str(err)}]})
        return self._json(200, {"errors": [], "warnings": []})

    def _create_repo(self) -> None:
        if not self._authorised():
            return self._json(401, {"error": "Invalid credentials"})
        payload = json.loads(self._body())
        repo_type = payload.get("type") or "model"
        repo_id = f"{payload['organization']}/{payload['name']}"
        url = f"{self.server.url}/{'datasets/' if repo_type == 'dataset' else ''}{repo_id}"
        if (repo_type, repo_id) in self.server.repos:  # the client reads the url of the existing one
            return self._json(409, {"error": "You already created this repo", "url": url})
        repo = Repo(private=payload.get("visibility") == "private")
        repo.commit("main", {".gitattributes": b""}, "initial commit")
        self.server.repos[(repo_type, repo_id)] = repo
        return self._json(200, {"url": url})

    def _commit(self, repo: Repo, type_path: str, repo_id: str, branch: str, body: bytes) -> None:
        lines = [json.loads(line) for line in body.splitlines() if line.strip()]
        header = next(line["value"] for line in lines if line["key"] == "header")
        files = {}
        for line in lines:
            if line["key"] != "file" or line["value"].get("encoding") != "base64":
                if line["key"] != "header":
                    return self._json(400, {"error": f"unsupported commit operation {line['key']}"})
                continue
            files[line["value"]["path"]] = base64.b64decode(line["value"]["content"])
        oid = repo.commit(branch, files, header["summary"])
        prefix = "" if type_path == "models" else f"{type_path}/"
        return self._json(200, {"commitUrl": f"{self.server.url}/{prefix}{repo_id}/commit/{oid}", "commitOid": oid})

    def do_HEAD(self) -> None:
        self._resolve()

    def do_GET(self) -> None:
        path = urlsplit(self.path).path
        if path == "/api/agent-harnesses":  # not a repository call: not in server.requests
            return self._json(200, {"standardEnvVars": [], "harnesses": {}})
        match = _INFO_RE.match(path)
        if match is None:
            return self._resolve()
        self.server.requests.append(("GET", path))
        with self.server.lock:
            repo = self._repo(match["type"].removesuffix("s"), match["repo"])
            if repo is None:
                return self._json(404, {"error": "Repository not found"}, "RepoNotFound")
            oid = repo.resolve(unquote(match["rev"]))
            if oid is None:
                return self._json(404, {"error": "Invalid rev id"}, "RevisionNotFound")
            tree = repo.commits[oid]
        if match["action"] == "revision":
            siblings = [{"rfilename": p} for p in sorted(tree)]
            return self._json(200, {"id": match["repo"], "sha": oid, "private": repo.private, "siblings": siblings})
        return self._tree(tree, unquote(match["path"] or ""), "recursive" in urlsplit(self.path).query)

    def _tree(self, tree: dict[str, bytes], folder: str, recursive: bool) -> None:
        prefix = f"{folder.strip('/')}/" if folder.strip("/") else ""
        entries: dict[str, dict[str, Any]] = {}
        for path, data in sorted(tree.items()):
            if not path.startswith(prefix):
                continue
            parts = path[len(prefix) :].split("/")
            if len(parts) > 1 and not recursive:
                entries.setdefault(prefix + parts[0], {"type": "directory", "path": prefix + parts[0], "oid": "0" * 40})
                continue
            for depth in range(1, len(parts)):  # the folders on the way down (recursive listings only)
                below = prefix + "/".join(parts[:depth])
                entries.setdefault(below, {"type": "directory", "path": below, "oid": "0" * 40})
            entries[path] = {"type": "file", "path": path, "size": len(data), "oid": _git_oid(data)}
        return self._json(200, list(entries.values()))

    def _resolve(self) -> None:
        path = urlsplit(self.path).path
        self.server.requests.append((self.command, path))
        match = _RESOLVE_RE.match(path)
        if match is None:
            return self._unhandled()
        with self.server.lock:
            repo = self._repo("dataset" if match["type"] else "model", match["repo"])
            if repo is None:
                return self._json(404, {"error": "Repository not found"}, "RepoNotFound")
            oid = repo.resolve(unquote(match["rev"]))
            if oid is None:
                return self._json(404, {"error": "Invalid rev id"}, "RevisionNotFound")
            data = repo.commits[oid].get(unquote(match["path"]))
        if data is None:
            return self._json(404, {"error": "Entry not found"}, "EntryNotFound")
        self._send(
            200, data, {"X-Repo-Commit": oid, "ETag": f'"{_git_oid(data)}"', "Content-Type": "application/octet-stream"}
        )


def _git_oid(data: bytes) -> str:
    """The git blob id of ``data`` (what the Hub sends as the ETag of a regular file)."""
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


@contextmanager
def running(tokens: set[str]) -> Iterator[HubServer]:
    """A started server (stopped and closed on exit)."""
    server = HubServer(tokens)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield server
    finally:
        server.shutdown()
        server.server_close()
