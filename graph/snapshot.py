"""Plan snapshots: a rerun with nothing changed skips planning (and importing the node modules).

After a successful run the engine saves what the plan resolved (keys, params, code versions) under
``cache/runs/plans/<fingerprint>.json``. The fingerprint covers everything planning reads: the
pipeline file (path and bytes), the overrides, the working directory, the interpreter, the
extra node modules, and the size and mtime of every source file of the engine and of the app's
node packages (sub-packages included); the files nodes read (``input_files()``) are checked by size and mtime too.
When the fingerprint matches and every entry is still in the cache, the run needs no planning at
all; anything else (a change, a miss, a ``cache: recompute|disable`` node) plans in full.
"""
from __future__ import annotations

import dataclasses
import hashlib
import importlib.util
import json
import os
import sys
from typing import Any

from .app import current
from .hashing import CACHE_FORMAT_SALT, canonical_json, digest_fields
from .store import ArtifactRef, Store



def _stat(path: str) -> list[Any]:
    try:
        st = os.stat(path)
    except OSError:
        return [path, None, None]
    return [path, st.st_mtime_ns, st.st_size]


def _source_files() -> list[str]:
    files: list[str] = []
    for package in (__package__, *current().node_packages):
        spec = importlib.util.find_spec(package)
        for folder in (spec.submodule_search_locations or []) if spec else []:
            for root, dirs, names in os.walk(folder):
                dirs[:] = sorted(d for d in dirs if d != "__pycache__")
                files += sorted(os.path.join(root, n) for n in names if n.endswith(".py"))
    for name in filter(None, (m.strip() for m in os.environ.get(current().node_modules_env, "").split(","))):
        try:
            spec = importlib.util.find_spec(name)
        except (ImportError, ValueError):
            spec = None
        files.append(spec.origin if spec and spec.origin else f"<missing {name}>")
    return files


def fingerprint(pipeline: str, overrides: list[str]) -> str | None:
    """Fingerprint of everything planning depends on, or None when the pipeline cannot be read."""
    try:
        with open(pipeline, "rb") as f:
            text = f.read()
    except OSError:
        return None
    fields = [CACHE_FORMAT_SALT, os.path.abspath(pipeline), hashlib.sha256(text).hexdigest(),
              canonical_json(overrides), os.getcwd(), sys.executable, sys.version,
              os.environ.get(current().node_modules_env, ""), canonical_json([_stat(p) for p in _source_files()])]
    return digest_fields(fields)


def _path(store: Store, fp: str) -> str:
    return os.path.join(store.local, "runs", "plans", fp + ".json")


@dataclasses.dataclass
class SnapshotInstance:
    """The parts of a planned instance that outputs, manifest and tables use."""

    node: str
    label: str
    branch: dict[str, Any]
    type_name: str
    is_sink: bool
    params_dump: dict[str, Any]
    key: str
    code_version: str
    cached: ArtifactRef | None = None
    runs: bool = False
    reason: str = ""

    @property
    def id(self) -> str:
        return f"{self.node}[{self.label}]" if self.label else self.node


@dataclasses.dataclass
class SnapshotPlan:
    """A plan rebuilt from a snapshot, where every instance is a cache hit."""

    file: str
    text_sha256: str
    overrides: list[str]  # the run's, the pipeline fallback's included when it ran
    instances: list[SnapshotInstance]
    store: Store
    fallback_outcome: dict[str, Any] | None = None  # what the pipeline's fallback read and did when the snapshot was saved

    @property
    def to_run(self) -> list[SnapshotInstance]:
        return []


def save(plan: Any, overrides: list[str], fallback: dict[str, Any] | None = None) -> None:
    """Remember a fully planned, successfully run plan under the run's ``overrides`` (see the module
    docstring); the plan's own overrides may add a pipeline fallback's (``fallback`` says why)."""
    fp = fingerprint(plan.file, overrides)
    if fp is None or any(i.decl.cache != "default" for i in plan.instances):
        return
    data = {
        "file": plan.file, "text_sha256": plan.text_sha256, "overrides": plan.overrides, "fallback": fallback,
        "input_files": sorted({p for i in plan.instances for p, _ in i.file_hashes}),
        "instances": [dataclasses.asdict(SnapshotInstance(
            i.node, i.label, i.branch, i.type_name, i.is_sink, i.params_dump, i.key, i.code_version))
            for i in plan.instances],
    }
    data["input_stats"] = [_stat(p) for p in data["input_files"]]
    path = _path(plan.store, fp)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    tmp = f"{path}.{os.getpid()}.tmp"
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(data, f)
    os.replace(tmp, path)


def load(pipeline: str, overrides: list[str], store: Store) -> SnapshotPlan | None:
    """The snapshot plan when nothing changed and every entry is cached, else None."""
    fp = fingerprint(pipeline, overrides)
    if fp is None:
        return None
    try:
        with open(_path(store, fp), encoding="utf-8") as f:
            data = json.load(f)
        if [_stat(p) for p in data["input_files"]] != data["input_stats"]:
            return None
        instances = [SnapshotInstance(**d) for d in data["instances"]]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    for inst in instances:
        inst.cached = store.lookup(inst.key)
        if inst.cached is None:
            return None
    return SnapshotPlan(data["file"], data["text_sha256"], list(data["overrides"]), instances, store,
                        data.get("fallback"))
