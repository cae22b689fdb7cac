"""Running a pipeline end to end (what the ``run`` command does), callable from Python too."""
from __future__ import annotations

import contextlib
import dataclasses
import os
import time
import uuid
from typing import Any, Callable

from . import plan as planning
from .app import current
from .errors import UserError
from .store import CorruptEntry, Store, default_cache_dir, open_store


@dataclasses.dataclass
class RunResult:
    plan: Any  # planning.Plan, or snapshot.SnapshotPlan when nothing changed since the last run
    status: dict[int, dict[str, Any]]  # id(instance) -> {"status": "ran"|"cached", "seconds": s} for those sent to run
    manifest: dict[str, Any]
    out_dir: str
    seconds: float
    repaired: list[str] = dataclasses.field(default_factory=list)  # damaged cache entries found and recomputed

    def ran(self) -> list[str]:
        """Ids (``node`` or ``node[branch]``) of the instances that actually ran."""
        return [i.id for i in self.plan.instances if self.status.get(id(i), {}).get("status") == "ran"]


def default_out_dir(pipeline: str) -> str:
    return os.path.join("out", os.path.splitext(os.path.basename(pipeline))[0])


def check_scheduler(scheduler: str) -> None:
    from .execute import SCHEDULERS

    if scheduler not in SCHEDULERS and not scheduler.startswith("tcp://"):
        raise UserError(f"--scheduler {scheduler!r}: expected one of {', '.join(SCHEDULERS)} or tcp://HOST:PORT")


def make_plan(pipeline: str, overrides: list[str] | None = None, cache_dir: str | None = None,
              targets: list[str] | None = None) -> planning.Plan:
    """The full plan, or with ``targets`` only those nodes and what they need (see :func:`.plan.restrict`)."""
    from .pipeline import load_pipeline

    plan = planning.expand(load_pipeline(pipeline, overrides or []), open_store(cache_dir or default_cache_dir()))
    return planning.restrict(plan, targets) if targets else plan


DAMAGED_RETRIES = 3
"""How many times a run re-plans after finding damaged cache entries before giving up."""


def preflight(out_dir: str, store: Store) -> None:
    """The checks that can fail cheaply, done before any node runs: the output folder can be
    written, the cache disk has room, ``SOURCE_DATE_EPOCH`` (if set) is usable."""
    from .outputs import check_out_dir, created_time

    check_out_dir(out_dir)
    store.check()
    created_time()


def run_pipeline(
    pipeline: str,
    overrides: list[str] | None = None,
    *,
    out_dir: str | None = None,
    scheduler: str = "auto",
    cache_dir: str | None = None,
    explain: bool = False,
    on_plan: Callable[[planning.Plan], None] | None = None,
    progress: Callable[[int], Any] | None = None,
    targets: list[str] | None = None,
) -> RunResult:
    """Plan, run what is missing, write the output folder; see :mod:`.execute`.

    ``on_plan`` sees the plan before anything runs (the CLI prints ``--explain`` there);
    ``progress(total)`` returns a context manager yielding an object with ``start(instance id)``
    and ``done(instance id)``. A cache entry found damaged on the way (its sha256 no longer matches)
    is discarded, and the run re-plans and recomputes it (listed in ``RunResult.repaired``).
    ``targets``: run only these nodes and what they need (their sinks alone fill the output folder).
    """
    from . import snapshot

    check_scheduler(scheduler)
    start = time.perf_counter()
    overrides = list(overrides or [])
    store = open_store(cache_dir or default_cache_dir())
    out_dir = out_dir or default_out_dir(pipeline)
    targets = list(targets or [])
    plan = None if targets else snapshot.load(pipeline, overrides, store)
    if plan is None:
        plan = make_plan(pipeline, overrides, store.root, targets)
    preflight(out_dir, store)
    if explain and isinstance(plan, planning.Plan):
        planning.explain(plan)
    if on_plan:
        on_plan(plan)
    status: dict[str, dict[str, Any]] = {}  # instance id -> status, kept across re-plans
    repaired: list[str] = []
    for attempt in range(DAMAGED_RETRIES + 1):
        try:
            manifest = _execute_and_write(plan, scheduler, out_dir, status, progress)
            break
        except CorruptEntry as exc:
            if attempt == DAMAGED_RETRIES:
                raise UserError(f"cache {store.root}: entries keep failing their sha256 check ({exc}); check the "
                                f"disk, or start afresh with `{current().name} cache clear`") from None
            repaired.append(str(exc))
            plan = make_plan(pipeline, overrides, store.root, targets)  # the damaged entry is a miss now
    if isinstance(plan, planning.Plan) and not targets:  # a partial plan would overwrite the full records
        planning.record_run(plan)
        snapshot.save(plan, overrides)
    for inst in plan.instances:
        if inst.cached is not None:
            plan.store.touch(inst.cached)
    by_instance = {id(i): status[i.id] for i in plan.instances if i.id in status}
    return RunResult(plan, by_instance, manifest, os.path.abspath(out_dir), time.perf_counter() - start, repaired)


def _execute_and_write(plan: Any, scheduler: str, out_dir: str, status: dict[str, dict[str, Any]],
                       progress: Callable[[int], Any] | None) -> dict[str, Any]:
    from .execute import execute, task_name
    from .outputs import write_outputs

    by_task = {task_name(i): i for i in plan.to_run}
    run_id = uuid.uuid4().hex
    bar = progress(len(by_task)) if progress else contextlib.nullcontext(None)
    try:
        with bar as events:
            def on_done(name: str, result: Any) -> None:
                inst = by_task[name]
                status[inst.id] = {"status": "ran" if result.ran else "cached", "seconds": result.seconds,
                                   "note": result.ref.note}
                if events is not None:
                    events.done(inst.id)

            def on_start(name: str) -> None:
                if events is not None:
                    events.start(by_task[name].id)

            results = execute(plan, scheduler, run_id, on_done, on_start)
        refs = {id(i): i.cached for i in plan.instances if i.cached is not None}
        refs.update({id(by_task[name]): result.ref for name, result in results.items()})
        by_instance = {id(i): status[i.id] for i in plan.instances if i.id in status}
        return write_outputs(plan, refs, out_dir, {"status": by_instance, "scheduler": scheduler})
    finally:
        plan.store.drop_scratch(run_id)
