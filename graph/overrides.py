"""``-S PATH=VALUE`` overrides of a parsed pipeline document."""
from __future__ import annotations

from typing import Any

import yaml

from .errors import UserError
from .pipeline import NODE_KEYS, TOP_KEYS, Document, did_you_mean


def apply_override(doc: Document, override: str) -> None:
    """Apply ``-S PATH=VALUE`` to the document (VALUE parsed as YAML).

    PATH is dotted into the document (``params.diagonal_mm``, ``nodes.remesh.params.target_edge_mm``,
    list items by index); ``NODE.PARAM`` is short for ``nodes.NODE.params.PARAM`` and a bare
    ``NAME`` for the pipeline param ``params.NAME``. Existing paths can
    be replaced; new keys are accepted only inside a node's ``params`` (checked against the node
    type later) and for a node's optional keys (``map``, ``cache``, ...).
    """
    where = f"-S {override}"
    path_text, eq, raw = override.partition("=")
    if not eq or not path_text:
        raise UserError(f"{where}: expected PATH=VALUE, e.g. -S params.diagonal_mm=200")
    try:
        value = yaml.safe_load(raw) if raw.strip() else None
    except yaml.YAMLError as exc:
        raise UserError(f"{where}: VALUE is not valid YAML ({getattr(exc, 'problem', exc)})") from None
    parts: list[str | int] = list(path_text.split("."))
    nodes = doc.data["nodes"]
    if parts[0] not in TOP_KEYS:
        if parts[0] in nodes and len(parts) == 2:
            parts = ["nodes", parts[0], "params", parts[1]]
        elif parts[0] in doc.data["params"] and len(parts) == 1:
            parts = ["params", parts[0]]
        else:
            choices = list(TOP_KEYS) + list(nodes) + list(doc.data["params"])
            raise UserError(f"{where}: unknown path {path_text!r}{did_you_mean(str(parts[0]), choices)} "
                            "(use NAME or params.NAME for pipeline params, NODE.PARAM or nodes.NODE.params.PARAM)")
    cur: Any = doc.data
    for i, part in enumerate(parts):
        last = i == len(parts) - 1
        done = ".".join(map(str, parts[:i])) or "<top>"
        if isinstance(cur, list):
            try:
                part = int(part)
                cur[part]
            except (ValueError, IndexError):
                raise UserError(f"{where}: {done} is a list of {len(cur)} items; {part!r} is not an index") from None
            parts[i] = part
        elif isinstance(cur, dict):
            if part not in cur:
                in_params = len(parts) >= 3 and parts[0] == "nodes" and parts[2] == "params" and i >= 2
                node_key = i == 2 and parts[0] == "nodes" and part in NODE_KEYS
                if not (in_params or node_key):
                    hint = did_you_mean(str(part), map(str, cur)) or f" (keys: {', '.join(map(str, cur)) or 'none'})"
                    raise UserError(f"{where}: {done} has no key {part!r}{hint}")
                if not last:
                    cur[part] = {}
        else:
            raise UserError(f"{where}: {done} is a value, not a mapping or list")
        if last:
            cur[part] = value
        else:
            cur = cur[part]
    prefix = tuple(parts)
    for marks in (doc.marks, doc.key_marks):
        for p in [p for p in marks if p[: len(prefix)] == prefix]:
            del marks[p]
    doc.marks[prefix] = where
    doc.key_marks[prefix] = where
