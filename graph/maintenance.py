"""The ``cache info|gc|clear`` commands.

``gc`` always removes temp dirs and scratch areas older than an hour (left by killed runs) and
entries that fail validation (meta.json, file sizes and every file's sha256); on object storage
also the files of losing or killed writers (see :mod:`.remote`), once an hour old. With pipelines given it drops the entries those pipelines do not use
(their current plans' keys are kept); with ``--older-than DAYS`` it drops entries not used (run or
hit) for that many days; with both, an entry must be unused by the pipelines AND old to go.
"""
from __future__ import annotations

import math
import os
import shutil
import time

from .errors import UserError
from .store import CorruptEntry, Store

STALE_TMP_SECONDS = 3600.0


def _count(path: str) -> int:
    return len(os.listdir(path)) if os.path.isdir(path) else 0


def info(store: Store) -> list[str]:
    entries = store.entries()
    size = sum(store.entry_size(folder) for _, folder in entries)
    local = store.local
    return [
        f"cache dir: {store.root}" + (f" (temp dirs, locks, run records, logs: {local})" if local != store.root else ""),
        f"entries:   {len(entries)} ({size / 1e6:.1f} MB)",
        f"temp dirs: {_count(os.path.join(local, 'tmp'))}, scratch runs: {_count(os.path.join(store.root, 'scratch'))}",
        f"pipelines with run records: {_count(os.path.join(local, 'runs'))}, crash logs: {_count(os.path.join(local, 'logs'))}",
    ]


def gc(store: Store, keep: set[str] | None, older_than_days: float | None) -> list[str]:
    if older_than_days is not None and not (math.isfinite(older_than_days) and older_than_days >= 0):
        raise UserError(f"--older-than {older_than_days:g}: DAYS must be a finite number of days >= 0, "
                        "e.g. --older-than 30")
    now = time.time()
    removed_tmp = 0
    for root in (os.path.join(store.local, "tmp"), os.path.join(store.root, "scratch")):
        for name in os.listdir(root) if os.path.isdir(root) else []:
            path = os.path.join(root, name)
            if now - os.path.getmtime(path) > STALE_TMP_SECONDS:
                shutil.rmtree(path, ignore_errors=True)
                removed_tmp += 1
    corrupt = dropped = freed = 0
    for key, folder in store.entries():
        try:
            store.verify(folder, key)
        except CorruptEntry:
            if store.being_written(folder, STALE_TMP_SECONDS):
                continue
            store.discard(folder)
            corrupt += 1
            continue
        removed_tmp += store.drop_orphans(folder, STALE_TMP_SECONDS)
        unused = keep is not None and key not in keep
        old = older_than_days is not None and store.entry_age_s(folder) > older_than_days * 86400
        if (keep is not None or older_than_days is not None) and \
                (unused or keep is None) and (old or older_than_days is None):
            freed += store.entry_size(folder)
            store.discard(folder)
            dropped += 1
    return [f"removed {removed_tmp} stale temp dirs, {corrupt} corrupt entries, "
            f"{dropped} unused entries ({freed / 1e6:.1f} MB)"]


def clear(store: Store) -> str:
    entries = len(store.entries())
    store.clear()
    return f"cleared {entries} entries from {store.root}"
