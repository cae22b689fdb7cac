"""Running a pipeline end to end (what the ``run`` command does), callable from Python too."""
from __future__ import annotations

import contextlib
import dataclasses
import os
import time
import uuid
from typing import Any, Callable

from . import plan as planning
from .errors import UserError
from .store import Store, default_cache_dir


@dataclasses.dataclass
class RunResult:
    plan: Any  # planning.Plan, or snapshot.SnapshotPlan when nothing changed since the last run
    status: dict[int, dict[str, Any]]  # id(instance) -> {"status": "ran"|"cached", "seconds": s} for those sent to run
    manifest: dict[str, Any]
    out_dir: str
    seconds: float

    def ran(self) -> list[str]:
        """Ids (``node`` or ``node[branch]``) of the instances that actually ran."""
        return [i.id for i in self.plan.instances if self.status.get(id(i), {}).get("status") == "ran"]


def default_out_dir(pipeline: str) -> str:
    return os.path.join("out", os.path.splitext(os.path.basename(pipeline))[0])


def check_scheduler(scheduler: str) -> None:
    from .execute import SCHEDULERS

    if scheduler not in SCHEDULERS and not scheduler.startswith("tcp://"):
        raise UserError(f"--scheduler {scheduler!r}: expected one of {', '.join(SCHEDULERS)} or tcp://HOST:PORT")


def make_plan(pipeline: str, overrides: list[str] | None = None, cache_dir: str | None = None) -> planning.Plan:
    from .pipeline import load_pipeline

    return planning.expand(load_pipeline(pipeline, overrides or []), Store(cache_dir or default_cache_dir()))


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
) -> RunResult:
    """Plan, run what is missing, write the output folder; see :mod:`.execute`.

    ``on_plan`` sees the plan before anything runs (the CLI prints ``--explain`` there);
    ``progress(total)`` returns a context manager yielding ``advance(instance id)``.
    """
    from . import snapshot
    from .execute import execute, task_name
    from .outputs import write_outputs

    check_scheduler(scheduler)
    start = time.perf_counter()
    overrides = list(overrides or [])
    store = Store(cache_dir or default_cache_dir())
    plan = snapshot.load(pipeline, overrides, store)
    if plan is None:
        plan = make_plan(pipeline, overrides, store.root)
    out_dir = out_dir or default_out_dir(pipeline)
    if explain and isinstance(plan, planning.Plan):
        planning.explain(plan)
    if on_plan:
        on_plan(plan)
    by_task = {task_name(i): i for i in plan.to_run}
    status: dict[int, dict[str, Any]] = {}
    run_id = uuid.uuid4().hex
    bar = progress(len(by_task)) if progress else contextlib.nullcontext(lambda label: None)
    try:
        with bar as advance:
            def on_done(name: str, result: Any) -> None:
                inst = by_task[name]
                status[id(inst)] = {"status": "ran" if result.ran else "cached", "seconds": result.seconds}
                advance(inst.id)

            results = execute(plan, scheduler, run_id, on_done)
        refs = {id(i): i.cached for i in plan.instances if i.cached is not None}
        refs.update({id(by_task[name]): result.ref for name, result in results.items()})
        manifest = write_outputs(plan, refs, out_dir, {"status": status, "scheduler": scheduler})
    finally:
        plan.store.drop_scratch(run_id)
    if isinstance(plan, planning.Plan):
        planning.record_run(plan)
        snapshot.save(plan, overrides)
    for inst in plan.instances:
        if inst.cached is not None:
            plan.store.touch(inst.cached)
    return RunResult(plan, status, manifest, os.path.abspath(out_dir), time.perf_counter() - start)
