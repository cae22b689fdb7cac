"""A cache on object storage through fsspec (``--cache-dir s3://bucket/prefix``, ``memory://...``).

Workers then need no shared filesystem: every process opens the same URL. Same keys as the local
store; entries are laid out as::

    objects/<key[:2]>/<key>/meta.json          the commit record, written last
    objects/<key[:2]>/<key>/<commit-id>/...    the artifact files of that commit

An object store has no atomic rename of folders, but a single object write is atomic: a writer
uploads its files under a fresh commit id, then writes ``meta.json`` naming that commit. A reader
sees either no ``meta.json`` (a miss) or one that names complete files (sizes checked on lookup,
every sha256 on load, as in the local store). Two writers of one key each upload their own commit
and the last ``meta.json`` wins; both commits are sound, the loser's files are left for
``cache gc`` (commit folders no ``meta.json`` names, older than an hour). Temp dirs, locks, run
records and logs stay on the local disk (``$XDG_CACHE_HOME/<app>/remote/<hash of the URL>``);
locks are per machine, so two machines may compute one key twice, never commit a broken entry.
A ``memory://`` cache lives in one process: use it with ``--scheduler sync`` or ``threads``.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
import uuid
from typing import Any

from . import artifacts
from .app import user_cache_dir
from .errors import UserError
from .hashing import file_sha256
from .store import META, META_FORMAT, ArtifactRef, CorruptEntry, Store, check_room

def local_dir_for(url: str) -> str:
    """The local folder holding the temp dirs, locks, run records and logs of a remote cache."""
    return os.path.join(user_cache_dir(), "remote", hashlib.sha256(url.encode()).hexdigest()[:16])


class RemoteStore(Store):
    """:class:`.store.Store` on an fsspec filesystem; ``ArtifactRef.path`` is the entry's fsspec path."""

    def __init__(self, url: str):
        import fsspec

        try:
            self.fs, base = fsspec.core.url_to_fs(url)
        except (ImportError, ValueError) as exc:
            raise UserError(f"--cache-dir {url}: {exc}") from None
        self.root = url.rstrip("/")
        self.base = base.rstrip("/")
        self.local = local_dir_for(self.root)
        protocols = (self.fs.protocol,) if isinstance(self.fs.protocol, str) else tuple(self.fs.protocol)
        self.in_process_only = "memory" in protocols
        """A memory:// filesystem exists in this process alone (worker processes would not see it)."""

    def check(self) -> None:
        check_room("cache", self.local, "set XDG_CACHE_HOME to a folder on another disk")
        probe = f"{self.base}/.write-test-{uuid.uuid4().hex[:8]}"
        try:
            self.fs.makedirs(self.base, exist_ok=True)  # creates the bucket when missing (and allowed)
            self.fs.pipe_file(probe, b"")
            self.fs.rm(probe)
        except Exception as exc:  # every backend has its own errors (botocore, aiohttp, ...)
            raise UserError(f"cache {self.root}: cannot reach or write it ({type(exc).__name__}: {exc}); check the "
                            "URL, the credentials and the endpoint (e.g. FSSPEC_S3_ENDPOINT_URL)") from None

    def entry_dir(self, key: str) -> str:
        return f"{self.base}/objects/{key[:2]}/{key}"

    def scratch_dir(self, run_id: str, key: str) -> str:
        return f"{self.base}/scratch/{run_id}/{key}"

    def _present(self, folder: str) -> bool:
        self.fs.invalidate_cache(folder)  # other machines write too: no listing cached from before
        return self.fs.exists(f"{folder}/{META}")

    def read_meta(self, folder: str, key: str) -> dict[str, Any]:
        self.fs.invalidate_cache(folder)
        try:
            meta = json.loads(self.fs.cat_file(f"{folder}/{META}"))
        except (OSError, ValueError) as exc:
            raise CorruptEntry(f"{self.root}: unreadable {folder}/{META}: {exc}") from None
        if not isinstance(meta, dict) or meta.get("format") != META_FORMAT or meta.get("key") != key \
                or not isinstance(meta.get("commit"), str):
            raise CorruptEntry(f"{folder}: {META} does not describe key {key}")
        try:
            sizes = {os.path.basename(i["name"].rstrip("/")): i["size"]
                     for i in self.fs.ls(f"{folder}/{meta['commit']}", detail=True)}
        except OSError:
            sizes = {}
        for name, info in meta.get("files", {}).items():
            if sizes.get(name) != info["size"]:
                raise CorruptEntry(f"{folder}: {name} has {sizes.get(name)} bytes, expected {info['size']}")
        return meta

    def _download(self, folder: str, key: str) -> str:
        """The entry's files in a fresh local temp dir, every sha256 checked."""
        meta = self.read_meta(folder, key)
        tmp = self._new_tmp()
        try:
            for name, info in meta["files"].items():
                local = os.path.join(tmp, name)
                self.fs.get_file(f"{folder}/{meta['commit']}/{name}", local)
                if file_sha256(local) != info["sha256"]:
                    raise CorruptEntry(f"{self.root}: {folder}/{name} does not match its recorded sha256")
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return tmp

    def verify(self, folder: str, key: str) -> dict[str, Any]:
        meta = self.read_meta(folder, key)
        shutil.rmtree(self._download(folder, key), ignore_errors=True)
        return meta

    def load(self, ref: ArtifactRef) -> Any:
        try:
            tmp = self._download(ref.path, ref.key)
        except CorruptEntry:
            self.discard(ref.path)
            raise
        try:
            return artifacts.decode(tmp, mmap=False)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    def touch(self, ref: ArtifactRef) -> None:
        """Object stores keep no usable access time: ``gc --older-than`` counts from the commit."""

    def _commit(self, tmp: str, final: str, key: str) -> None:
        with open(os.path.join(tmp, META), encoding="utf-8") as f:
            meta = json.load(f)
        meta["commit"] = uuid.uuid4().hex
        for name in meta["files"]:
            self.fs.put_file(os.path.join(tmp, name), f"{final}/{meta['commit']}/{name}")
        self.fs.pipe_file(f"{final}/{META}", json.dumps(meta, indent=1, sort_keys=True).encode())

    def discard(self, folder: str) -> None:
        """Delete ``meta.json`` first (the entry is a miss from then on), then its files."""
        for path in (f"{folder}/{META}", folder):
            try:
                self.fs.rm(path, recursive=True)
            except (FileNotFoundError, OSError):
                pass

    def drop_scratch(self, run_id: str) -> None:
        try:
            self.fs.rm(f"{self.base}/scratch/{run_id}", recursive=True)
        except (FileNotFoundError, OSError):
            pass

    def _ls(self, path: str) -> list[str]:
        self.fs.invalidate_cache(path)
        try:
            return sorted(os.path.basename(p.rstrip("/")) for p in self.fs.ls(path, detail=False))
        except (FileNotFoundError, OSError):
            return []

    def entries(self) -> list[tuple[str, str]]:
        objects = f"{self.base}/objects"
        return [(key, f"{objects}/{prefix}/{key}") for prefix in self._ls(objects)
                for key in self._ls(f"{objects}/{prefix}")]

    def entry_size(self, folder: str) -> int:
        return sum(self.fs.du(folder, total=False).values()) if self.fs.exists(folder) else 0

    def entry_age_s(self, folder: str) -> float:
        try:
            return time.time() - self.fs.modified(f"{folder}/{META}").timestamp()
        except (FileNotFoundError, OSError, NotImplementedError):
            return 0.0

    def _age_s(self, path: str) -> float:
        """Seconds since the newest file under ``path`` was written."""
        try:
            return time.time() - max(self.fs.modified(p).timestamp() for p in self.fs.find(path))
        except (ValueError, OSError, NotImplementedError):
            return float("inf")

    def being_written(self, folder: str, grace_s: float) -> bool:
        """No meta.json yet and files younger than ``grace_s``: a writer may be uploading."""
        return not self.fs.exists(f"{folder}/{META}") and self._age_s(folder) < grace_s

    def drop_orphans(self, folder: str, grace_s: float) -> int:
        """Delete the commit folders of ``folder`` that its meta.json does not name (left by a
        losing or killed writer) once older than ``grace_s``; return how many."""
        try:
            named = json.loads(self.fs.cat_file(f"{folder}/{META}")).get("commit")
        except (OSError, ValueError):
            named = None
        dropped = 0
        for name in self._ls(folder):
            path = f"{folder}/{name}"
            if name == META or name == named:
                continue
            if self._age_s(path) > grace_s:
                self.fs.rm(path, recursive=True)
                dropped += 1
        return dropped

    def clear(self) -> None:
        for area in ("objects", "scratch"):
            try:
                self.fs.rm(f"{self.base}/{area}", recursive=True)
            except (FileNotFoundError, OSError):
                pass
        for area in ("tmp", "locks", "runs", "logs"):
            shutil.rmtree(os.path.join(self.local, area), ignore_errors=True)
