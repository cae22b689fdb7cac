"""Node outputs on disk without pickle: a JSON tree plus ``.npy``/``.bin`` files.

:func:`encode` writes ``value.json`` and one file per array/bytes blob into a folder and returns
their names; :func:`decode` reads them back. The JSON tree tags every non-JSON value:

* ``{"$tuple": [...]}``, ``{"$dict": {...}}`` (string keys only), ``{"$float": "nan"|"inf"|"-inf"}``
* ``{"$array": "a3.npy"}`` numpy arrays and numpy scalars (``"$scalar": true``); loaded with
  ``allow_pickle=False`` (object dtypes are refused when writing), large arrays memory-mapped
* ``{"$bytes": "b0.bin"}``, ``{"$files": {"mesh.ply": "b1.bin", ...}}`` (a sink's :class:`Files`)
* ``{"$dataclass": "module:QualName", "fields": {...}}`` frozen dataclasses and
  ``{"$enum": "module:QualName", "value": 3}`` IntEnum members; decoding imports the class only if
  its module is inside one of the app's node packages (or one of the extra node modules the engine
  was told about).
"""
from __future__ import annotations

import dataclasses
import enum
import importlib
import json
import math
import os
from typing import Any, BinaryIO, Callable

import numpy as np

from .app import current
from .node import Files

VALUE_FILE = "value.json"
MMAP_MIN_BYTES = 1 << 24
"""Arrays at least this large are memory-mapped on load instead of read into memory."""

TRUSTED_PREFIXES: list[str] = []
"""Module prefixes whose classes :func:`decode` may import besides the app's node packages (the
engine appends extra node modules)."""


class ArtifactError(Exception):
    """A value cannot be stored, or a stored artifact is malformed."""


def _qualname(cls: type) -> str:
    return f"{cls.__module__}:{cls.__qualname__}"


def _trusted(module: str) -> bool:
    prefixes = [*TRUSTED_PREFIXES, *(p + "." for p in current().node_packages)]
    return any(module == p.rstrip(".") or module.startswith(p) for p in prefixes)


def _import_class(qualified: str) -> type:
    module, _, qualname = qualified.partition(":")
    if not _trusted(module):
        raise ArtifactError(f"refusing to import class {qualified!r}: not from a {current().name} module")
    obj: Any = importlib.import_module(module)
    for part in qualname.split("."):
        obj = getattr(obj, part)
    return obj


def encode(value: Any, folder: str) -> list[str]:
    """Write ``value`` into ``folder`` (which must exist); return the names of the files written."""
    names: list[str] = []

    def blob(prefix: str, suffix: str, write: Callable[[BinaryIO], None]) -> str:
        name = f"{prefix}{len(names)}{suffix}"
        with open(os.path.join(folder, name), "wb") as f:
            write(f)
        names.append(name)
        return name

    def save_array(arr: np.ndarray, where: str) -> str:
        if arr.dtype.hasobject:
            raise ArtifactError(f"{where}: object arrays cannot be stored (use a numeric dtype)")
        return blob("a", ".npy", lambda f: np.save(f, np.ascontiguousarray(arr), allow_pickle=False))

    def walk(v: Any, where: str) -> Any:
        if v is None or isinstance(v, (bool, str)):
            return v
        if isinstance(v, enum.IntEnum):
            return {"$enum": _qualname(type(v)), "value": int(v)}
        if isinstance(v, int):
            return v
        if isinstance(v, float):
            return v if math.isfinite(v) else {"$float": repr(v)}
        if isinstance(v, np.ndarray):
            return {"$array": save_array(v, where)}
        if isinstance(v, np.generic):
            return {"$array": save_array(np.asarray(v), where), "$scalar": True}
        if isinstance(v, (bytes, bytearray)):
            return {"$bytes": blob("b", ".bin", lambda f: f.write(bytes(v)))}
        if isinstance(v, Files):
            out = {}
            for path, data in sorted(v.contents.items()):
                if not isinstance(path, str) or not isinstance(data, (bytes, bytearray)):
                    raise ArtifactError(f"{where}: Files maps str paths to bytes, got {path!r}")
                out[path] = blob("b", ".bin", lambda f, d=data: f.write(bytes(d)))
            return {"$files": out}
        if isinstance(v, list):
            return [walk(x, f"{where}[{i}]") for i, x in enumerate(v)]
        if isinstance(v, tuple):
            return {"$tuple": [walk(x, f"{where}[{i}]") for i, x in enumerate(v)]}
        if isinstance(v, dict):
            bad = [k for k in v if not isinstance(k, str)]
            if bad:
                raise ArtifactError(f"{where}: dict keys must be str, got {bad[0]!r}")
            return {"$dict": {k: walk(x, f"{where}.{k}") for k, x in v.items()}}
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            cls = type(v)
            if not cls.__dataclass_params__.frozen:  # type: ignore[attr-defined]
                raise ArtifactError(f"{where}: dataclass {cls.__qualname__} must be frozen")
            if not _trusted(cls.__module__):
                raise ArtifactError(f"{where}: dataclass {_qualname(cls)} is not from a {current().name} module")
            fields = {f.name: walk(getattr(v, f.name), f"{where}.{f.name}") for f in dataclasses.fields(v)}
            return {"$dataclass": _qualname(cls), "fields": fields}
        raise ArtifactError(f"{where}: values of type {type(v).__qualname__} cannot be stored")

    tree = walk(value, "output")
    with open(os.path.join(folder, VALUE_FILE), "w", encoding="utf-8") as f:
        json.dump(tree, f, allow_nan=False, separators=(",", ":"))
    names.append(VALUE_FILE)
    return names


def decode(folder: str, mmap: bool = True) -> Any:
    """Read a value written by :func:`encode` from ``folder`` (``mmap=False``: every array is read
    into memory, for folders deleted right after)."""
    with open(os.path.join(folder, VALUE_FILE), encoding="utf-8") as f:
        tree = json.load(f)

    def read_bytes(name: str) -> bytes:
        with open(os.path.join(folder, name), "rb") as f:
            return f.read()

    def walk(v: Any) -> Any:
        if isinstance(v, list):
            return [walk(x) for x in v]
        if not isinstance(v, dict):
            return v
        if "$array" in v:
            path = os.path.join(folder, v["$array"])
            mode = "r" if mmap and os.path.getsize(path) >= MMAP_MIN_BYTES else None
            arr = np.load(path, allow_pickle=False, mmap_mode=mode)
            return arr[()] if v.get("$scalar") else arr
        if "$tuple" in v:
            return tuple(walk(x) for x in v["$tuple"])
        if "$dict" in v:
            return {k: walk(x) for k, x in v["$dict"].items()}
        if "$float" in v:
            return float(v["$float"])
        if "$bytes" in v:
            return read_bytes(v["$bytes"])
        if "$files" in v:
            return Files({path: read_bytes(name) for path, name in v["$files"].items()})
        if "$enum" in v:
            return _import_class(v["$enum"])(v["value"])
        if "$dataclass" in v:
            cls = _import_class(v["$dataclass"])
            return cls(**{k: walk(x) for k, x in v["fields"].items()})
        raise ArtifactError(f"{folder}: unknown tag in {VALUE_FILE}: {sorted(v)}")

    return walk(tree)
