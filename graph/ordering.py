"""Which of the tasks ready at once starts first: a node's ``priority:``, then the most estimated work
from the task to the end of the run (its own seconds plus the longest chain of seconds after it,
HEFT's upward rank), so that no worker idles at the end while a long chain that started late runs.

The estimates are each node instance's seconds in earlier runs (:data:`TIMINGS_NAME`, a
:mod:`.userstate` record by instance id ``node[branch]``, shared by every cache folder and object);
an instance never timed counts as the median of those that were. On a first run every estimate is
equal, so the rank counts the tasks after each one; dask's own order decides among equal ranks. The
order never changes a result.
"""
from __future__ import annotations

import statistics
from typing import Any

from .userstate import read_record, write_record

TIMINGS_NAME = "timings.json"
TIMINGS_ENTRIES = 4000  # the most recent instances the record keeps


def record_timings(seconds: dict[str, float]) -> None:
    """Add the seconds (by instance id) of the instances a run computed to the record."""
    if not seconds:
        return
    record = read_record(TIMINGS_NAME)
    for instance_id, value in seconds.items():
        record.pop(instance_id, None)  # re-inserted last: the newest entries are the ones kept
        record[instance_id] = round(float(value), 3)
    write_record(TIMINGS_NAME, record, TIMINGS_ENTRIES)


def start_order(tasks: dict[str, tuple[Any, list]], priorities: dict[str, int]) -> dict[str, float]:
    """Per task name (``tasks`` in topological order, each ``(spec with instance_id, args naming
    upstream tasks)``): ``priority + rank / (1 + largest rank)``; higher starts first."""
    record = read_record(TIMINGS_NAME)
    known = [float(v) for v in record.values() if isinstance(v, (int, float))]
    fallback = statistics.median(known) if known else 1.0
    dependents: dict[str, list[str]] = {name: [] for name in tasks}
    for name, (_, args) in tasks.items():
        for up in args:
            if isinstance(up, str) and up in dependents:
                dependents[up].append(name)
    rank: dict[str, float] = {}
    for name in reversed(list(tasks)):
        own = record.get(tasks[name][0].instance_id)
        own = float(own) if isinstance(own, (int, float)) else fallback
        rank[name] = own + max((rank[d] for d in dependents[name]), default=0.0)
    scale = 1.0 + max(rank.values(), default=0.0)
    return {name: priorities[name] + rank[name] / scale for name in tasks}
