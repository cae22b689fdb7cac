"""The on-disk artifact store (the cache).

Layout under the cache dir::

    objects/<key[:2]>/<key>/   meta.json + the artifact files (see artifacts.py)
    tmp/<pid>-<uuid>/          entries being written by process pid; renamed into objects/ when complete
    scratch/<run-id>/<key>/    outputs of ``cache: disable`` nodes, deleted after the run
    locks/<key[:2]>/<key>.lock per-key file locks (two runs sharing a cache compute a key once)
    runs/<pipeline-id>.json    what each node of a pipeline last ran with (for ``--explain``)
    logs/                      tracebacks of unexpected node failures

An entry is committed by writing its files and then ``meta.json`` (last) into ``tmp/<uuid>/`` and
renaming that folder to ``objects/..../<key>``; if the rename finds the key already present,
another writer won and the copy is discarded. ``meta.json`` records the size and sha256 of every
file and the sha256 of the whole content. A lookup accepts an entry only when meta.json parses,
names the right key and every file has its recorded size; loading also checks every sha256.
Anything else (a writer killed mid-way, a truncated file, a missing meta.json) is a miss: the
entry is moved aside and deleted, and the node recomputes.
"""
from __future__ import annotations

import dataclasses
import errno
import hashlib
import json
import os
import shutil
import time
import uuid
from typing import Any

from . import artifacts
from .app import current
from .errors import UserError
from .hashing import file_sha256

META = "meta.json"
META_FORMAT = "graph.artifact/1"
MIN_FREE_BYTES = 64 << 20
"""A run does not start when the cache or the output disk has less room than this."""
DISK_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM)
"""Write errors the operator can fix (room, permissions), reported in one line instead of a traceback."""


def disk_problem(what: str, path: str, exc: OSError, fix: str) -> UserError:
    """The one-line error for a write to ``path`` that failed with one of :data:`DISK_ERRNOS`."""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return UserError(f"{what} {path}: no space left on the device; free some space or {fix}")
    return UserError(f"{what} {path} is not writable ({exc.strerror}); {fix}")


def check_room(what: str, path: str, fix: str, probe_at: str | None = None, min_free: int = MIN_FREE_BYTES) -> None:
    """Fail early when ``path`` (or its nearest existing parent; ``probe_at`` instead when given)
    cannot take a write: read-only, not a folder, or under ``min_free`` bytes free."""
    probe = os.path.abspath(probe_at or path)
    while not os.path.exists(probe):
        probe = os.path.dirname(probe)
    if not os.path.isdir(probe):
        raise UserError(f"{what} {path}: {probe} is a file, not a folder; name a folder there or {fix}")
    test_dir = os.path.join(probe, f".write-test-{uuid.uuid4().hex[:8]}")
    try:
        os.mkdir(test_dir)
        os.rmdir(test_dir)
        stats = os.statvfs(probe)
    except OSError as exc:
        raise disk_problem(what, path, exc, fix) from None
    free = stats.f_bavail * stats.f_frsize
    if free < min_free:
        raise UserError(f"{what} {path}: only {free / 1e6:.1f} MB free on its disk (at least {min_free / 1e6:.0f} MB "
                        f"needed); free some space or {fix}")


def is_url(root: str) -> bool:
    """Whether a cache root names object storage through fsspec (``s3://...``, ``memory://...``)."""
    return "://" in root and not root.startswith("file://")


def default_cache_dir() -> str:
    """``$<APP>_CACHE_DIR`` (see :mod:`.app`) or ``./cache`` relative to the current directory."""
    root = os.environ.get(current().cache_env) or "cache"
    return root if is_url(root) else os.path.abspath(root)


def open_store(root: str) -> "Store":
    """The store at ``root``: a local folder, or object storage for a URL (see :mod:`.remote`)."""
    if is_url(root):
        from .remote import RemoteStore

        return RemoteStore(root)
    return Store(root.removeprefix("file://"))


@dataclasses.dataclass(frozen=True)
class ArtifactRef:
    """A stored node output, passed between tasks instead of the value itself."""

    key: str
    path: str  # the entry folder
    content_sha256: str
    seconds: float  # how long the node took when it was computed
    note: str | None = None  # the node's one-line note on this output (``note=`` of graph.node.node)


class CorruptEntry(Exception):
    """A stored entry failed validation (it is never used; the run recomputes it)."""


_VERIFIED: dict[str, tuple[Any, ...]] = {}
"""Entry folder -> its recorded content sha256 and its files' (inode, size, mtime in ns) when this
process last checked their sha256."""


def _check_hashes(folder: str, meta: dict[str, Any]) -> None:
    for name, info in meta["files"].items():
        if file_sha256(os.path.join(folder, name)) != info["sha256"]:
            raise CorruptEntry(f"{folder}: {name} does not match its recorded sha256")


def _stamp(folder: str, meta: dict[str, Any]) -> tuple[Any, ...]:
    try:
        stats = [os.stat(os.path.join(folder, name)) for name in sorted(meta["files"])]
    except OSError as exc:
        raise CorruptEntry(f"{folder}: {exc}") from None
    return (meta["content_sha256"], *((st.st_ino, st.st_size, st.st_mtime_ns) for st in stats))


class Store:
    """Artifacts addressed by cache key under one cache dir."""

    def __init__(self, root: str):
        self.root = os.path.abspath(root)
        self.local = self.root
        """Local folder for temp dirs, locks, run records and logs (the root itself, here)."""
        self.in_process_only = False
        """Whether only this process can see the entries (then nodes must run in this process)."""

    def check(self) -> None:
        """Fail early when the cache cannot take writes (read-only, full disk)."""
        check_room("cache", self.root, "pass --cache-dir on another disk")

    # -- paths --------------------------------------------------------------------------------
    def entry_dir(self, key: str) -> str:
        return os.path.join(self.root, "objects", key[:2], key)

    def scratch_dir(self, run_id: str, key: str) -> str:
        return os.path.join(self.root, "scratch", run_id, key)

    def lock_path(self, key: str) -> str:
        return os.path.join(self.local, "locks", key[:2], key + ".lock")

    def _new_tmp(self) -> str:
        path = os.path.join(self.local, "tmp", f"{os.getpid()}-{uuid.uuid4().hex}")
        os.makedirs(path)
        return path

    def drop_tmp_of(self, pids: list[int]) -> None:
        """Remove the temp folders of (killed) writer processes ``pids``."""
        root = os.path.join(self.local, "tmp")
        prefixes = tuple(f"{pid}-" for pid in pids)
        for name in os.listdir(root) if os.path.isdir(root) and prefixes else []:
            if name.startswith(prefixes):
                shutil.rmtree(os.path.join(root, name), ignore_errors=True)

    # -- reading ------------------------------------------------------------------------------
    def read_meta(self, folder: str, key: str) -> dict[str, Any]:
        """meta.json of an entry after the cheap checks (parses, right key, file sizes)."""
        try:
            with open(os.path.join(folder, META), encoding="utf-8") as f:
                meta = json.load(f)
        except (OSError, ValueError) as exc:
            raise CorruptEntry(f"{folder}: unreadable {META}: {exc}") from None
        if not isinstance(meta, dict) or meta.get("format") != META_FORMAT or meta.get("key") != key:
            raise CorruptEntry(f"{folder}: {META} does not describe key {key}")
        for name, info in meta.get("files", {}).items():
            try:
                size = os.path.getsize(os.path.join(folder, name))
            except OSError:
                raise CorruptEntry(f"{folder}: missing file {name}") from None
            if size != info["size"]:
                raise CorruptEntry(f"{folder}: {name} has {size} bytes, expected {info['size']}")
        return meta

    def lookup(self, key: str) -> ArtifactRef | None:
        """The committed entry for ``key``, or None (a corrupt entry is discarded)."""
        folder = self.entry_dir(key)
        if not self._present(folder):
            return None
        try:
            meta = self.read_meta(folder, key)
        except CorruptEntry:
            self.discard(folder)
            return None
        return ArtifactRef(key, folder, meta["content_sha256"], meta.get("seconds", 0.0), meta.get("note"))

    def verify(self, folder: str, key: str) -> dict[str, Any]:
        """meta.json of an entry after the full check: :meth:`read_meta` and every file's sha256."""
        meta = self.read_meta(folder, key)
        _check_hashes(folder, meta)
        return meta

    def load(self, ref: ArtifactRef) -> Any:
        """The stored value; every file's sha256 is checked first (a damaged entry is discarded
        and :class:`CorruptEntry` raised: the caller recomputes it).

        As DVC's state database does, a file this process has already hashed is not hashed again
        while its inode, size and modification time are unchanged (a sweep's branches load the
        same large inputs, e.g. the samples' distance fields, dozens of times per worker)."""
        try:
            meta = self.read_meta(ref.path, ref.key)
            stamp = _stamp(ref.path, meta)
            if _VERIFIED.get(ref.path) != stamp:
                _check_hashes(ref.path, meta)
                _VERIFIED[ref.path] = stamp
        except CorruptEntry:
            _VERIFIED.pop(ref.path, None)
            self.discard(ref.path)
            raise
        return artifacts.decode(ref.path)

    def _present(self, folder: str) -> bool:
        return os.path.isdir(folder)

    def touch(self, ref: ArtifactRef) -> None:
        """Mark an entry as used now (``cache gc --older-than`` looks at this)."""
        try:
            os.utime(ref.path)
        except OSError:
            pass

    # -- writing ------------------------------------------------------------------------------
    def write(self, key: str, value: Any, *, info: dict[str, Any], scratch_run: str | None = None) -> ArtifactRef:
        """Store ``value`` under ``key`` atomically and return its reference.

        ``scratch_run`` stores into the run's scratch area instead of the cache (``cache: disable``).
        A full or read-only cache disk is a :class:`.errors.UserError`.
        """
        try:
            return self._write(key, value, info, scratch_run)
        except OSError as exc:
            if exc.errno in DISK_ERRNOS:
                raise disk_problem("cache", self.root, exc, "pass --cache-dir on another disk") from None
            raise

    def _write(self, key: str, value: Any, info: dict[str, Any], scratch_run: str | None) -> ArtifactRef:
        tmp = self._new_tmp()
        try:
            names = artifacts.encode(value, tmp)
            files = {}
            for name in names:
                path = os.path.join(tmp, name)
                files[name] = {"size": os.path.getsize(path), "sha256": file_sha256(path)}
            content = json.dumps(sorted((n, f["sha256"]) for n, f in files.items()))
            meta = {
                "format": META_FORMAT,
                "key": key,
                "files": files,
                "content_sha256": hashlib.sha256(content.encode()).hexdigest(),
                "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                **info,
            }
            with open(os.path.join(tmp, META), "w", encoding="utf-8") as f:
                json.dump(meta, f, indent=1, sort_keys=True)
                f.flush()
                os.fsync(f.fileno())
            final = self.scratch_dir(scratch_run, key) if scratch_run else self.entry_dir(key)
            self._commit(tmp, final, key)
            return ArtifactRef(key, final, meta["content_sha256"], info.get("seconds", 0.0), info.get("note"))
        finally:
            if os.path.exists(tmp):
                shutil.rmtree(tmp, ignore_errors=True)

    def _commit(self, tmp: str, final: str, key: str) -> None:
        os.makedirs(os.path.dirname(final), exist_ok=True)
        for _ in range(3):
            try:
                os.rename(tmp, final)
                return
            except OSError as exc:
                if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                    raise
            try:  # another writer committed first: keep theirs if it is sound
                self.read_meta(final, key)
                return
            except CorruptEntry:
                self.discard(final)
        raise OSError(f"could not commit cache entry {final}")

    def replace(self, key: str, value: Any, *, info: dict[str, Any]) -> ArtifactRef:
        """Store ``value`` under ``key``, replacing an existing entry (``cache: recompute``)."""
        folder = self.entry_dir(key)
        if self._present(folder):
            self.discard(folder)
        return self.write(key, value, info=info)

    def discard(self, folder: str) -> None:
        """Remove an entry: first move it aside (so it is never seen half-deleted), then delete."""
        aside = os.path.join(self.root, "tmp", "discard-" + uuid.uuid4().hex)
        os.makedirs(os.path.dirname(aside), exist_ok=True)
        try:
            os.rename(folder, aside)
        except FileNotFoundError:
            return
        shutil.rmtree(aside, ignore_errors=True)

    def drop_scratch(self, run_id: str) -> None:
        shutil.rmtree(os.path.join(self.root, "scratch", run_id), ignore_errors=True)

    def being_written(self, folder: str, grace_s: float) -> bool:
        """Whether an entry that fails validation may still be in the middle of its commit (never,
        here: a folder appears in objects/ complete, by one rename)."""
        return False

    def drop_orphans(self, folder: str, grace_s: float) -> int:
        """Delete files of ``folder`` that its meta.json does not name (none can exist here)."""
        return 0

    def entry_size(self, folder: str) -> int:
        """Bytes of an entry's files."""
        return sum(os.path.getsize(os.path.join(folder, n)) for n in os.listdir(folder)) if os.path.isdir(folder) else 0

    def entry_age_s(self, folder: str) -> float:
        """Seconds since the entry was last used (written or hit)."""
        return time.time() - os.path.getmtime(folder)

    def clear(self) -> None:
        """Delete every entry, lock, run record, log and temp dir."""
        for area in ("objects", "tmp", "scratch", "locks", "runs", "logs"):
            shutil.rmtree(os.path.join(self.root, area), ignore_errors=True)

    # -- maintenance ----------------------------------------------------------------------------
    def entries(self) -> list[tuple[str, str]]:
        """``(key, folder)`` of every folder under objects/ (sound or not)."""
        out = []
        objects = os.path.join(self.root, "objects")
        if not os.path.isdir(objects):
            return out
        for prefix in sorted(os.listdir(objects)):
            sub = os.path.join(objects, prefix)
            if os.path.isdir(sub):
                out += [(key, os.path.join(sub, key)) for key in sorted(os.listdir(sub))]
        return out
