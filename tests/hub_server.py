"""A small Hugging Face hub on 127.0.0.1 for tests: the routes the real ``huggingface_hub`` client uses to
create a dataset repo, commit files (regular uploads), tag, list refs and the tree, and resolve files.

Written by hand because no hub server package is available from the package index; it keeps every
commit's snapshot so tags resolve to what they pointed at. ``refuse`` makes every write answer 403."""

from __future__ import annotations

import base64
import hashlib
import json
import re
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import parse_qs, unquote, urlparse


def git_blob_sha(data: bytes) -> str:
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


class Repo:
    def __init__(self) -> None:
        empty = hashlib.sha1(b"empty").hexdigest()
        self.snapshots: dict[str, dict[str, bytes]] = {empty: {}}
        self.branches = {"main": empty}
        self.tags: dict[str, str] = {}

    def resolve(self, rev: str) -> str | None:
        if rev in self.branches:
            return self.branches[rev]
        if rev in self.tags:
            return self.tags[rev]
        return rev if rev in self.snapshots else None


class LocalHub:
    def __init__(self) -> None:
        self.repos: dict[str, Repo] = {}
        self.refuse = False
        self.lock = threading.Lock()
        self.server = ThreadingHTTPServer(("127.0.0.1", 0), self._handler())
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)

    def __enter__(self) -> LocalHub:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.server.shutdown()
        self.server.server_close()

    def _handler(self):
        hub = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args) -> None:
                pass

            def _send(self, status: int, body=b"", headers: dict | None = None, head: bool = False) -> None:
                if not isinstance(body, bytes):
                    body = json.dumps(body).encode()
                    headers = {"Content-Type": "application/json", **(headers or {})}
                self.send_response(status)
                for key, value in (headers or {}).items():
                    self.send_header(key, value)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                if not head:
                    self.wfile.write(body)

            def _not_found(self, code: str = "RepoNotFound") -> None:
                self._send(404, {"error": code}, {"X-Error-Code": code, "X-Error-Message": code})

            def _body(self) -> bytes:
                return self.rfile.read(int(self.headers.get("Content-Length", 0)))

            def _repo(self, repo_id: str) -> Repo | None:
                return hub.repos.get(repo_id)

            def do_HEAD(self) -> None:
                self._get(head=True)

            def do_GET(self) -> None:
                self._get(head=False)

            def _get(self, head: bool) -> None:
                url = urlparse(self.path)
                path = unquote(url.path)
                if m := re.fullmatch(r"/datasets/([^/]+/[^/]+)/resolve/([^/]+)/(.+)", path):
                    repo = self._repo(m[1])
                    sha = repo.resolve(m[2]) if repo else None
                    if sha is None:
                        return self._not_found("RevisionNotFound" if repo else "RepoNotFound")
                    data = repo.snapshots[sha].get(m[3])
                    if data is None:
                        return self._not_found("EntryNotFound")
                    etag = f'"{git_blob_sha(data)}"'
                    return self._send(200, data, {"X-Repo-Commit": sha, "ETag": etag}, head=head)
                if m := re.fullmatch(r"/api/datasets/([^/]+/[^/]+)/refs", path):
                    repo = self._repo(m[1])
                    if repo is None:
                        return self._not_found()
                    refs = {
                        "branches": [
                            {"name": n, "ref": f"refs/heads/{n}", "targetCommit": s} for n, s in repo.branches.items()
                        ],
                        "tags": [{"name": n, "ref": f"refs/tags/{n}", "targetCommit": s} for n, s in repo.tags.items()],
                        "converts": [],
                    }
                    return self._send(200, refs)
                if m := re.fullmatch(r"/api/datasets/([^/]+/[^/]+)/tree/([^/]+)(/.*)?", path):
                    repo = self._repo(m[1])
                    sha = repo.resolve(m[2]) if repo else None
                    if sha is None:
                        return self._not_found()
                    prefix = (m[3] or "").strip("/")
                    recursive = parse_qs(url.query).get("recursive", ["false"])[0].lower() == "true"
                    return self._send(200, self._tree(repo.snapshots[sha], prefix, recursive))
                if m := re.fullmatch(r"/api/datasets/([^/]+/[^/]+)(?:/revision/([^/]+))?", path):
                    repo = self._repo(m[1])
                    sha = repo.resolve(m[2] or "main") if repo else None
                    if sha is None:
                        return self._not_found()
                    files = repo.snapshots[sha]
                    info = {
                        "id": m[1],
                        "sha": sha,
                        "private": False,
                        "disabled": False,
                        "gated": False,
                        "tags": [],
                        "siblings": [{"rfilename": p} for p in sorted(files)],
                        "lastModified": "2026-01-01T00:00:00.000Z",
                    }
                    return self._send(200, info, head=head)
                self._not_found()

            @staticmethod
            def _tree(files: dict[str, bytes], prefix: str, recursive: bool) -> list[dict]:
                entries, dirs = [], set()
                for name in sorted(files):
                    if prefix and not name.startswith(prefix + "/"):
                        continue
                    rest = name[len(prefix) + 1 :] if prefix else name
                    if "/" in rest and not recursive:
                        dirs.add((prefix + "/" if prefix else "") + rest.split("/")[0])
                        continue
                    data = files[name]
                    entries.append({"type": "file", "path": name, "size": len(data), "oid": git_blob_sha(data)})
                    if recursive:
                        parts = name.split("/")[:-1]
                        dirs.update("/".join(parts[: i + 1]) for i in range(len(parts)))
                dirs = {d for d in dirs if not prefix or d.startswith(prefix + "/")}
                return [{"type": "directory", "path": d, "oid": "0" * 40} for d in sorted(dirs)] + entries

            def do_POST(self) -> None:
                path = unquote(urlparse(self.path).path)
                body = self._body()
                if path == "/api/validate-yaml":
                    return self._send(200, {})
                if hub.refuse:
                    return self._send(403, {"error": "write access refused"}, {"X-Error-Message": "refused"})
                if path == "/api/repos/create":
                    payload = json.loads(body)
                    org = payload.get("organization")
                    repo_id = f"{org}/{payload['name']}" if org else payload["name"]
                    with hub.lock:
                        if repo_id in hub.repos:
                            return self._send(409, {"error": "exists", "url": f"{hub.url}/datasets/{repo_id}"})
                        hub.repos[repo_id] = Repo()
                    return self._send(200, {"url": f"{hub.url}/datasets/{repo_id}", "name": repo_id})
                if m := re.fullmatch(r"/api/datasets/([^/]+/[^/]+)/preupload/([^/]+)", path):
                    files = json.loads(body)["files"]
                    modes = [{"path": f["path"], "uploadMode": "regular", "shouldIgnore": False} for f in files]
                    return self._send(200, {"files": modes, "commitOid": None})
                if m := re.fullmatch(r"/api/datasets/([^/]+/[^/]+)/commit/([^/]+)", path):
                    return self._commit(m[1], m[2], body)
                if m := re.fullmatch(r"/api/datasets/([^/]+/[^/]+)/tag/([^/]+)", path):
                    repo = self._repo(m[1])
                    sha = repo.resolve(m[2]) if repo else None
                    if sha is None:
                        return self._not_found()
                    repo.tags[json.loads(body)["tag"]] = sha
                    return self._send(200, {})
                self._not_found()

            def _commit(self, repo_id: str, branch: str, body: bytes) -> None:
                repo = self._repo(repo_id)
                if repo is None or branch not in repo.branches:
                    return self._not_found()
                with hub.lock:
                    files = dict(repo.snapshots[repo.branches[branch]])
                    for line in body.decode().splitlines():
                        if not line.strip():
                            continue
                        item = json.loads(line)
                        if item["key"] == "file":
                            files[item["value"]["path"]] = base64.b64decode(item["value"]["content"])
                        elif item["key"] == "deletedFile":
                            files.pop(item["value"]["path"], None)
                    digest = hashlib.sha1()
                    for name in sorted(files):
                        digest.update(name.encode() + git_blob_sha(files[name]).encode())
                    digest.update(repo.branches[branch].encode())
                    sha = digest.hexdigest()
                    repo.snapshots[sha] = files
                    repo.branches[branch] = sha
                self._send(200, {"commitUrl": f"{hub.url}/datasets/{repo_id}/commit/{sha}", "commitOid": sha})

            def do_DELETE(self) -> None:
                path = unquote(urlparse(self.path).path)
                if hub.refuse:
                    return self._send(403, {"error": "write access refused"})
                if m := re.fullmatch(r"/api/datasets/([^/]+/[^/]+)/tag/([^/]+)", path):
                    repo = self._repo(m[1])
                    if repo is None or m[2] not in repo.tags:
                        return self._not_found("RevisionNotFound")
                    del repo.tags[m[2]]
                    return self._send(200, {})
                self._not_found()

        return Handler
