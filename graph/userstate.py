"""Small JSON records kept per user in :func:`.app.user_cache_dir` and shared by every result cache
(the code-version memo, the tasks' durations): hints only, so a record that is missing, unreadable
or cannot be written costs the next run time, never a result."""
from __future__ import annotations

import json
import os
import uuid

from .app import user_cache_dir


def read_record(name: str) -> dict:
    """The JSON object ``name`` in the user's cache folder; empty when there is none or it cannot be
    read."""
    try:
        with open(os.path.join(user_cache_dir(), name), encoding="utf-8") as f:
            data = json.load(f)
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def write_record(name: str, data: dict, keep: int) -> None:
    """Write the newest ``keep`` entries of ``data`` as ``name`` into the user's cache folder, atomically."""
    folder = user_cache_dir()
    kept = dict(list(data.items())[-keep:])
    tmp = os.path.join(folder, f".{name}.{os.getpid()}-{uuid.uuid4().hex}")
    try:
        os.makedirs(folder, exist_ok=True)
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(kept, f)
        os.replace(tmp, os.path.join(folder, name))
    except OSError:
        try:
            os.unlink(tmp)
        except OSError:
            pass
