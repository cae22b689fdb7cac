"""Cache keys: sha256 recipe hashes over a length-prefixed encoding.

A node instance's key covers, in this order: the cache-format salt, the pipeline node name and type,
its branch (the mapped values that select it), its code version, its canonical params JSON, the
content hashes of the files it reads, and the sorted ``input name -> upstream keys`` pairs (Merkle
style, so a change anywhere upstream changes every key below it). Each field is written as an
8-byte big-endian length followed by its UTF-8 bytes, so no two field sequences encode alike.
Keys are computed from the recipe alone, before anything runs.
"""
from __future__ import annotations

import hashlib
import json
from typing import Any, Iterable

CACHE_FORMAT_SALT = "graph.cache/1"
"""Bump when the artifact layout or the key recipe changes: every old entry becomes a miss."""


def canonical_json(value: Any) -> str:
    """JSON with sorted keys and no insignificant whitespace (the hashed form of params)."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=False)


def digest_fields(fields: Iterable[str | bytes]) -> str:
    """sha256 hex of the length-prefixed concatenation of ``fields``."""
    h = hashlib.sha256()
    for field in fields:
        data = field.encode("utf-8") if isinstance(field, str) else field
        h.update(len(data).to_bytes(8, "big"))
        h.update(data)
    return h.hexdigest()


def file_sha256(path: str, chunk: int = 1 << 20) -> str:
    """sha256 hex of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def instance_key(
    *,
    node_name: str,
    node_type: str,
    branch: dict[str, Any],
    code_version: str,
    params_json: str,
    file_hashes: list[tuple[str, str]],
    inputs: dict[str, list[tuple[str, str]]],
) -> str:
    """The cache key of one node instance.

    ``inputs`` maps each input name to the ``(upstream key, output name)`` pairs feeding it (one
    pair for a plain input, one per branch, in branch order, for a fan-in ``node[*]``).
    """
    fields: list[str] = [
        CACHE_FORMAT_SALT,
        "node", node_name,
        "type", node_type,
        "branch", canonical_json(branch),
        "code", code_version,
        "params", params_json,
        "files", canonical_json(file_hashes),
    ]
    for name in sorted(inputs):
        fields += ["input", name, canonical_json(inputs[name])]
    return digest_fields(fields)
