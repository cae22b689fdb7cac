"""The output folder: sink files plus ``manifest.json``, replaced as a whole.

``manifest.json`` is specified by ``graph/schemas/manifest.schema.json`` (format version
:data:`MANIFEST_FORMAT_VERSION`, named in its ``format`` field).

Everything is written into a temporary sibling folder (manifest.json last), then swapped in with
renames, so the output folder is never seen half-written. Sinks of mapped nodes write under a
sub-folder named after their branch (``target_edge_mm=2/mesh.ply``).
"""
from __future__ import annotations

import errno
import hashlib
import importlib.metadata
import json
import os
import platform
import posixpath
import shutil
import stat
import time
import uuid
from typing import Any

from . import interrupts
from .app import current
from .errors import UserError
from .node import Files
from .store import DISK_ERRNOS, ArtifactRef, check_room, disk_problem

MANIFEST = "manifest.json"
MANIFEST_FORMAT_VERSION = 2
"""Bump with graph/schemas/manifest.schema.json when the manifest's fields change."""
ENGINE_VERSIONED = ("numpy", "pydantic", "dask", "distributed", "pyyaml")
"""Distributions the engine itself runs on; the app adds its own (:attr:`.app.App.versioned`)."""


def _versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for dist in dict.fromkeys((current().name, *current().versioned, *ENGINE_VERSIONED)):
        try:
            out[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            continue
    return out


def _safe_relpath(path: str, node: str) -> str:
    norm = posixpath.normpath(path)
    if posixpath.isabs(norm) or norm.startswith("..") or norm in (".", MANIFEST):
        raise UserError(f"node {node}: output file name {path!r} is not a relative path inside the output folder")
    return norm


OUT_FIX = "choose another --out"


def check_out_dir(out_dir: str) -> None:
    """Fail before anything runs when ``out_dir`` cannot become the output folder: it is a file, a
    folder this app did not write, or its disk is read-only or full."""
    out_dir = os.path.abspath(out_dir)
    if _not_a_folder(out_dir):
        raise UserError(f"--out {out_dir} is a file, not a folder; {OUT_FIX} (a new folder or a previous output "
                        "folder)")
    if _foreign(out_dir):
        raise UserError(f"--out {out_dir} exists and was not written by {current().name} (no {MANIFEST}); "
                        "choose a new or empty folder")
    check_room("--out", out_dir, OUT_FIX, probe_at=os.path.dirname(out_dir))  # where the new folder is written


def _not_a_folder(path: str) -> bool:
    """Whether ``path`` exists and is not a folder, by one ``stat``: a run swapping the same output
    folder moves it away and back, so two checks could see it exist and then not be a folder."""
    try:
        return not stat.S_ISDIR(os.stat(path).st_mode)
    except (FileNotFoundError, NotADirectoryError):
        return False


def write_outputs(plan: Any, refs: dict[int, ArtifactRef], out_dir: str, run: dict[str, Any]) -> dict[str, Any]:
    """Write every sink's files and the manifest into ``out_dir``; return the manifest.

    ``refs`` maps ``id(instance)`` to the reference of its output; ``run`` holds per-run facts
    (overrides, scheduler, per-instance status and seconds) copied into the manifest. A damaged
    sink entry raises :class:`.store.CorruptEntry` (the runner recomputes it); a full or read-only
    disk is a one-line UserError, and ``out_dir`` is left as it was.
    """
    out_dir = os.path.abspath(out_dir)
    check_out_dir(out_dir)
    try:
        return _write(plan, refs, out_dir, run)
    except OSError as exc:
        if exc.errno in DISK_ERRNOS:
            raise disk_problem("--out", out_dir, exc, OUT_FIX) from None
        raise


def _write(plan: Any, refs: dict[int, ArtifactRef], out_dir: str, run: dict[str, Any]) -> dict[str, Any]:
    parent = os.path.dirname(out_dir)
    os.makedirs(parent, exist_ok=True)
    tmp = os.path.join(parent, f".{os.path.basename(out_dir)}.tmp-{uuid.uuid4().hex[:8]}")
    os.makedirs(tmp)
    try:
        files: dict[str, dict[str, Any]] = {}
        for inst in plan.instances:
            if not inst.is_sink:
                continue
            value = plan.store.load(refs[id(inst)])
            if not isinstance(value, Files):
                raise UserError(f"sink node {inst.id} produced {type(value).__name__}, not Files")
            for path, data in value.contents.items():
                rel = _safe_relpath(posixpath.join(_branch_dir(inst), path), inst.id)
                if rel in files:
                    raise UserError(f"nodes {files[rel]['node']} and {inst.id} both write {rel}; rename one")
                target = os.path.join(tmp, *rel.split("/"))
                os.makedirs(os.path.dirname(target), exist_ok=True)
                with open(target, "wb") as f:
                    f.write(data)
                files[rel] = {"sha256": hashlib.sha256(data).hexdigest(), "size": len(data), "node": inst.id}
        manifest = _manifest(plan, refs, files, run)
        with open(os.path.join(tmp, MANIFEST), "w", encoding="utf-8") as f:
            json.dump(manifest, f, indent=1)
        with interrupts.deferred():  # never stopped between moving the old folder away and the new one in
            _swap(tmp, out_dir)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return manifest


def _foreign(out_dir: str) -> bool:
    """Whether ``out_dir`` holds files but no manifest.json (not written by this app). A run
    swapping the same folder at that moment can make one listing look foreign (the old folder is
    listed while it is deleted), so a foreign listing is confirmed twice, 50 ms apart."""
    for _ in range(3):
        try:
            entries = os.listdir(out_dir)
        except (FileNotFoundError, NotADirectoryError):
            return False
        if not entries or MANIFEST in entries:
            return False
        time.sleep(0.05)
    return True


def _branch_dir(inst: Any) -> str:
    return "".join(c if c.isalnum() or c in "=,.-_" else "_" for c in inst.label) if inst.label else ""


def _swap(tmp: str, out_dir: str) -> None:
    """Replace ``out_dir`` by ``tmp`` with two renames (retried if a concurrent run swaps too)."""
    old = f"{tmp}.old"
    for _ in range(10):
        try:
            os.rename(out_dir, old)
        except FileNotFoundError:
            pass
        try:
            os.rename(tmp, out_dir)
            break
        except OSError as exc:
            if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                raise
        finally:
            shutil.rmtree(old, ignore_errors=True)
    else:
        raise UserError(f"could not replace {out_dir}: other runs keep writing it")


def created_time() -> float:
    """Now, or ``$SOURCE_DATE_EPOCH`` when set (reproducible builds: https://reproducible-builds.org)."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH", "").strip()
    if not epoch:
        return time.time()
    try:
        return float(int(epoch))
    except ValueError:
        raise UserError(f"SOURCE_DATE_EPOCH={epoch!r} is not a whole number of seconds since 1970; "
                        "set it to e.g. $(git log -1 --format=%ct) or unset it") from None


def _manifest(plan: Any, refs: dict[int, ArtifactRef], files: dict[str, Any], run: dict[str, Any]) -> dict[str, Any]:
    nodes = []
    for inst in plan.instances:
        status = run["status"].get(id(inst), {})
        ref = refs.get(id(inst))
        nodes.append({
            "node": inst.node, "branch": inst.branch and {k: v for k, v in inst.branch.items()}, "label": inst.label,
            "type": inst.type_name, "params": inst.params_dump, "key": inst.key,
            "code_version": inst.code_version, "status": status.get("status", "cached"),
            "seconds": status.get("seconds", 0.0), "content_sha256": ref.content_sha256 if ref else None,
            "note": ref.note if ref else None,
        })
    return {
        "format": f"{current().name}.manifest/{MANIFEST_FORMAT_VERSION}",
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(created_time())),
        "pipeline": {"path": os.path.abspath(plan.file), "sha256": plan.text_sha256},
        "overrides": plan.overrides,
        "fallback": run.get("fallback"),
        "scheduler": run["scheduler"],
        "cache_dir": plan.store.root,
        "files": dict(sorted(files.items())),
        "nodes": nodes,
        "versions": _versions(),
    }
