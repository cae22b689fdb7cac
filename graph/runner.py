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
    fallback: dict[str, Any] | None = None  # what the pipeline's fallback read and did (.fallback), None without one

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

    ``on_plan`` sees the plan before anything runs (the CLI prints ``--explain`` there), and the
    wider plan too when a ``fallback:`` runs one (:mod:`.fallback`, full runs only);
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

    def planned(p: Any) -> None:
        if explain and isinstance(p, planning.Plan):
            planning.explain(p)
        if on_plan:
            on_plan(p)

    planned(plan)
    status: dict[str, dict[str, Any]] = {}  # instance id -> status, kept across re-plans and the fallback's two parts
    repaired: list[str] = []
    fallback = plan.fallback_outcome if isinstance(plan, snapshot.SnapshotPlan) else None
    if isinstance(plan, planning.Plan) and plan.pipeline.fallback and not targets:
        plan, fallback = _run_fallback(plan, pipeline, store, scheduler, status, progress, repaired)
        if plan.overrides != overrides:
            planned(plan)
    plan, manifest = _repairing(plan, lambda p: make_plan(pipeline, p.overrides, store.root, targets), repaired,
                                lambda p: _execute_and_write(p, scheduler, out_dir, status, progress, fallback))
    if isinstance(plan, planning.Plan) and not targets:  # a partial plan would overwrite the full records
        planning.record_run(plan)
        snapshot.save(plan, overrides, fallback)
    for inst in plan.instances:
        if inst.cached is not None:
            plan.store.touch(inst.cached)
    by_instance = {id(i): status[i.id] for i in plan.instances if i.id in status}
    return RunResult(plan, by_instance, manifest, os.path.abspath(out_dir), time.perf_counter() - start, repaired,
                     fallback)


def _repairing(plan: Any, replan: Callable[[Any], Any], repaired: list[str], work: Callable[[Any], Any]) -> tuple[Any, Any]:
    """``(plan, work(plan))``, planning afresh (``replan(plan)``) after each damaged cache entry found."""
    for attempt in range(DAMAGED_RETRIES + 1):
        try:
            return plan, work(plan)
        except CorruptEntry as exc:
            if attempt == DAMAGED_RETRIES:
                raise UserError(f"cache {plan.store.root}: entries keep failing their sha256 check ({exc}); check the "
                                f"disk, or start afresh with `{current().name} cache clear`") from None
            repaired.append(str(exc))
            plan = replan(plan)  # the damaged entry is a miss now
    raise AssertionError("unreachable")


def _run_fallback(plan: planning.Plan, pipeline: str, store: Store, scheduler: str, status: dict[str, dict[str, Any]],
                  progress: Callable[[int], Any] | None, repaired: list[str]) -> tuple[planning.Plan, dict[str, Any]]:
    """Run the ``fallback:``'s node and what it needs, read its value, and return the plan to run on
    (the wider one, planned before anything runs, when the value falls short; its cache hits decided
    afresh, so what just ran is one) and :meth:`.fallback.Fallback.outcome`."""
    fallback = plan.pipeline.fallback
    try:
        wider_plan = make_plan(pipeline, plan.overrides + list(fallback.overrides), store.root)
    except UserError as exc:
        raise UserError(f"{fallback.set_where}: fallback set: {exc}") from None
    if [i.key for i in wider_plan.instances] == [i.key for i in plan.instances]:
        return plan, fallback.outcome(None)
    first = planning.restrict(plan, [fallback.node])
    node = [i for i in first.instances if i.node == fallback.node]
    if len(node) != 1:
        raise UserError(f"{fallback.where}: fallback value {fallback.value_name}: node {fallback.node!r} has "
                        f"{len(node)} branches; name a node with one (a fan-in)")
    run_id = uuid.uuid4().hex
    try:
        first, refs = _repairing(first, lambda p: planning.restrict(make_plan(pipeline, p.overrides, store.root),
                                                                    [fallback.node]), repaired,
                                 lambda p: _execute(p, scheduler, run_id, status, progress))
        node = [i for i in first.instances if i.node == fallback.node][0]
        value = fallback.read(store.load(refs[id(node)]))
    finally:
        store.drop_scratch(run_id)
    return planning.refresh(wider_plan if fallback.falls_short(value) else plan), fallback.outcome(value)


def _execute(plan: Any, scheduler: str, run_id: str, status: dict[str, dict[str, Any]],
             progress: Callable[[int], Any] | None) -> dict[int, Any]:
    """Run what the plan misses; ``id(instance)`` -> its output's reference, for every instance (those
    of ``cache: disable`` nodes in the run's scratch area, which the caller drops when done)."""
    from .execute import execute, task_name

    by_task = {task_name(i): i for i in plan.to_run}
    bar = progress(len(by_task)) if progress else contextlib.nullcontext(None)
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
    return refs


def _execute_and_write(plan: Any, scheduler: str, out_dir: str, status: dict[str, dict[str, Any]],
                       progress: Callable[[int], Any] | None, fallback: dict[str, Any] | None) -> dict[str, Any]:
    from .outputs import write_outputs

    run_id = uuid.uuid4().hex
    try:
        refs = _execute(plan, scheduler, run_id, status, progress)
        by_instance = {id(i): status[i.id] for i in plan.instances if i.id in status}
        return write_outputs(plan, refs, out_dir, {"status": by_instance, "scheduler": scheduler,
                                                   "fallback": fallback})
    finally:
        plan.store.drop_scratch(run_id)
