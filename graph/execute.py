"""Execution: only the instances that must run go to a scheduler; artifacts travel by reference.

Each task (:func:`run_task`) loads its inputs from the store by :class:`ArtifactRef`, calls the node
function, writes the output to the store and returns the new reference, so the task graph never
embeds arrays. A per-key file lock makes concurrent runs sharing a cache compute each key once.

Schedulers (``--scheduler``):

* ``auto`` (default): when at least two instances could run at once, dask's multiprocessing
  scheduler with one worker process per core (forked on Linux, so the pool starts in ~0.1 s with the
  node modules already imported); otherwise in-process. Nothing of dask is imported when everything
  is cached. (A ``dask.distributed.LocalCluster`` costs ~0.45 s more to start and stop, which on
  2 cores eats most of the gain of a sweep of half-second branches: see bench/engine.py.)
* ``sync``: in-process, one instance at a time (debugging, profiling).
* ``threads`` / ``processes``: dask's local threaded / multiprocessing schedulers.
* ``local-cluster``: a ``dask.distributed.LocalCluster`` (one single-threaded worker process per
  core), started for this run only.
* ``tcp://HOST:PORT``: an existing dask.distributed scheduler. Its workers need the app installed
  and the cache: the same path on a shared filesystem, or object storage for all
  (``--cache-dir s3://bucket/prefix``, see :mod:`.remote`).

On every scheduler but ``sync``, of the tasks ready at once those of a node with a higher
``priority:`` start first, then those with the most estimated work after them (:mod:`.ordering`): a
long branch started last would leave the other workers idle at the end. Every run records its
instances' seconds for the next one's estimates.
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import os
import sys
import time
import traceback
from typing import Any, Callable

from filelock import FileLock

from . import artifacts, registry
from .app import App, configure, current
from .errors import NodeFailed, UserError
from .node import REGISTRY, Files
from .ordering import record_timings, start_order
from .plan import Instance, Plan
from .store import DISK_ERRNOS, ArtifactRef, CorruptEntry, Store, disk_problem, open_store

SCHEDULERS = ("auto", "sync", "threads", "processes", "local-cluster")


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """Everything a worker needs to run one instance (plain data, cheap to ship)."""

    instance_id: str
    node_type: str
    params: dict[str, Any]
    key: str
    cache_root: str
    cache_mode: str
    run_id: str
    app: App
    extra_modules: tuple[str, ...]
    # input name -> fan-in?, [(positional ref index, output name, upstream has one output?)]
    inputs: tuple[tuple[str, bool, tuple[tuple[int, str, bool], ...]], ...]


@dataclasses.dataclass(frozen=True)
class TaskResult:
    ref: ArtifactRef
    ran: bool  # False when a concurrent run had committed the key first
    seconds: float


def run_task(spec: TaskSpec, *refs: ArtifactRef) -> TaskResult:
    """Run one node instance (in whatever process the scheduler chose).

    A damaged input entry raises :class:`.store.CorruptEntry` (the entry is already discarded; the
    runner recomputes it and tries again); a full or read-only cache is a one-line UserError.
    """
    configure(spec.app)
    registry.load([spec.node_type], spec.extra_modules)
    artifacts.TRUSTED_PREFIXES[:] = sorted(set(artifacts.TRUSTED_PREFIXES) | {m + "." for m in spec.extra_modules})
    store = open_store(spec.cache_root)
    lock_path = store.lock_path(spec.key)
    try:
        os.makedirs(os.path.dirname(lock_path), exist_ok=True)
        lock = FileLock(lock_path)
        lock.acquire()
    except OSError as exc:
        if exc.errno in DISK_ERRNOS:
            raise disk_problem("cache", store.root, exc, "pass --cache-dir on another disk") from None
        raise
    try:
        if spec.cache_mode == "default":
            existing = store.lookup(spec.key)
            if existing is not None:
                return TaskResult(existing, False, 0.0)
        return _compute(spec, store, refs)
    except (UserError, CorruptEntry):
        raise
    except Exception as exc:
        log = _write_log(store, spec, traceback.format_exc())
        raise NodeFailed(f"node {spec.instance_id} failed: {type(exc).__name__}: {exc} (traceback: {log})") from None
    finally:
        lock.release()


def _compute(spec: TaskSpec, store: Store, refs: tuple[ArtifactRef, ...]) -> TaskResult:
    node = REGISTRY[spec.node_type]
    loaded: dict[int, Any] = {}
    kwargs: dict[str, Any] = {}
    for name, fan_in, items in spec.inputs:
        values = []
        for index, output, single in items:
            if index not in loaded:
                loaded[index] = store.load(refs[index])
            values.append(loaded[index] if single else loaded[index][output])
        kwargs[name] = values if fan_in else values[0]
    params = node.params.model_validate(spec.params)
    start = time.perf_counter()
    try:
        value = node.func(params, **kwargs)
    except UserError as exc:
        raise UserError(f"node {spec.instance_id}: {exc}") from None
    seconds = time.perf_counter() - start
    _check_output(node.name, node.outputs, node.sink, value)
    info = {"node": spec.instance_id, "type": spec.node_type, "seconds": seconds, "note": node.note_of(value)}
    if spec.cache_mode == "disable":
        ref = store.write(spec.key, value, info=info, scratch_run=spec.run_id)
    elif spec.cache_mode == "recompute":
        ref = store.replace(spec.key, value, info=info)
    else:
        ref = store.write(spec.key, value, info=info)
    return TaskResult(ref, True, seconds)


def _check_output(name: str, outputs: tuple[str, ...], sink: bool, value: Any) -> None:
    if sink and not isinstance(value, Files):
        raise TypeError(f"sink node {name} must return Files, got {type(value).__name__}")
    if len(outputs) > 1 and (not isinstance(value, dict) or set(value) != set(outputs)):
        got = sorted(value) if isinstance(value, dict) else type(value).__name__
        raise TypeError(f"node {name} must return a dict with keys {list(outputs)}, got {got}")


def _write_log(store: Store, spec: TaskSpec, text: str) -> str:
    folder = os.path.join(store.local, "logs")
    os.makedirs(folder, exist_ok=True)
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%S")
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in spec.instance_id)
    path = os.path.join(folder, f"{stamp}-{safe}-{spec.key[:8]}.log")
    with open(path, "w", encoding="utf-8") as f:
        f.write(f"node {spec.instance_id} ({spec.node_type}), key {spec.key}\nparams {spec.params}\n\n{text}")
    return path


# -- building the task graph -------------------------------------------------------------------
def task_name(inst: Instance) -> str:
    return f"{inst.id}-{inst.key[:16]}"


def build_tasks(plan: Plan, run_id: str) -> dict[str, tuple[TaskSpec, list[str | ArtifactRef]]]:
    """Task name -> (spec, positional args: names of upstream tasks or refs of cache hits)."""
    extra = tuple(registry.extra_modules())
    tasks: dict[str, tuple[TaskSpec, list[str | ArtifactRef]]] = {}
    for inst in plan.to_run:
        args: list[str | ArtifactRef] = []
        slots: dict[int, int] = {}
        inputs = []
        for name, ups in inst.inputs.items():
            items = []
            for up, output in ups:
                if id(up) not in slots:
                    slots[id(up)] = len(args)
                    args.append(task_name(up) if up.runs else up.cached)  # type: ignore[arg-type]
                items.append((slots[id(up)], output, len(up.decl.spec.outputs) == 1))
            inputs.append((name, any(ref.fan_in for ref in inst.decl.inputs[name]), tuple(items)))
        spec = TaskSpec(inst.id, inst.decl.spec.name, inst.params.model_dump(mode="json"), inst.key,
                        plan.store.root, inst.decl.cache, run_id, current(), extra, tuple(inputs))
        tasks[task_name(inst)] = (spec, args)
    return tasks


def parallel_width(plan: Plan) -> int:
    """Largest number of to-run instances at the same dependency depth (how many could run at once)."""
    depth: dict[int, int] = {}
    for inst in plan.to_run:
        ups = [depth[id(u)] for ups in inst.inputs.values() for u, _ in ups if id(u) in depth]
        depth[id(inst)] = 1 + max(ups, default=0)
    counts: dict[int, int] = {}
    for d in depth.values():
        counts[d] = counts.get(d, 0) + 1
    return max(counts.values(), default=0)


# -- schedulers --------------------------------------------------------------------------------
Done = Callable[[str, TaskResult], None]
Started = Callable[[str], None]


def _ignore_start(name: str) -> None:
    pass


def execute(plan: Plan, scheduler: str, run_id: str, on_done: Done, on_start: Started = _ignore_start) -> dict[str, TaskResult]:
    """Run ``plan.to_run``; ``on_start(task name)`` is called as each is handed to a worker (not on a
    dask.distributed cluster) and ``on_done(task name, result)`` as each finishes."""
    tasks = build_tasks(plan, run_id)
    if not tasks:
        return {}
    in_process = plan.store.in_process_only
    if scheduler == "auto":
        parallel = parallel_width(plan) >= 2 and (os.cpu_count() or 1) >= 2
        scheduler = ("threads" if in_process else "processes") if parallel else "sync"
    elif in_process and scheduler not in ("sync", "threads"):
        raise UserError(f"--cache-dir {plan.store.root} lives in this process only, which --scheduler {scheduler} "
                        "cannot share; use --scheduler sync or threads, or a cache on disk or object storage (s3://...)")
    distributed = scheduler == "local-cluster" or scheduler.startswith("tcp://")
    if scheduler not in ("sync", "threads", "processes") and not distributed:
        raise UserError(f"--scheduler {scheduler!r}: expected one of {', '.join(SCHEDULERS)} or tcp://HOST:PORT")
    if scheduler == "sync":  # one task at a time, in topological order: no start order to choose
        results = _run_sync(tasks, on_done, on_start)
    else:
        order = start_order(tasks, {task_name(inst): inst.decl.priority for inst in plan.to_run})
        results = (_run_distributed(tasks, order, scheduler, on_done) if distributed
                   else _run_dask_local(tasks, order, scheduler, on_done, on_start))
    record_timings({tasks[name][0].instance_id: result.seconds for name, result in results.items() if result.ran})
    return results


_nodes_ran_in_process = False


def _run_sync(tasks: dict[str, tuple[TaskSpec, list[str | ArtifactRef]]], on_done: Done, on_start: Started) -> dict[str, TaskResult]:
    global _nodes_ran_in_process
    _nodes_ran_in_process = True
    results: dict[str, TaskResult] = {}
    for name, (spec, args) in tasks.items():  # built in topological order
        refs = [results[a].ref if isinstance(a, str) else a for a in args]
        on_start(name)
        results[name] = run_task(spec, *refs)
        on_done(name, results[name])
    return results


def _ref_of(result: TaskResult | ArtifactRef) -> ArtifactRef:
    return result.ref if isinstance(result, TaskResult) else result


def _run_from_results(spec: TaskSpec, *upstream: TaskResult | ArtifactRef) -> TaskResult:
    return run_task(spec, *(_ref_of(u) for u in upstream))


def _dask_graph(tasks: dict[str, tuple[TaskSpec, list[str | ArtifactRef]]]) -> dict[str, Any]:
    return {name: (_run_from_results, spec, *args) for name, (spec, args) in tasks.items()}


def _run_dask_local(tasks: dict[str, tuple[TaskSpec, list[str | ArtifactRef]]], order: dict[str, float], kind: str,
                    on_done: Done, on_start: Started) -> dict[str, TaskResult]:
    import dask
    from dask.callbacks import Callback

    global _nodes_ran_in_process

    def in_start_order(ready: list) -> None:
        # dask.local pops its ready stack from the end; a stable sort keeps dask's order among equal keys
        ready.sort(key=order.__getitem__)

    class Progress(Callback):
        def _start_state(self, dsk: Any, state: Any) -> None:
            in_start_order(state["ready"])

        def _pretask(self, key: Any, dsk: Any, state: Any) -> None:
            on_start(key)

        def _posttask(self, key: Any, result: Any, dsk: Any, state: Any, worker_id: Any) -> None:
            on_done(key, result)
            in_start_order(state["ready"])

    names = list(tasks)
    # chunksize=1: one node instance per submission, so uneven branches balance across workers and
    # progress is reported per instance (dask's multiprocessing default batches 6 tasks at a time).
    with Progress(), dask.config.set({"chunksize": 1}):
        if kind == "threads":
            _nodes_ran_in_process = True
            from dask.threaded import get

            values = get(_dask_graph(tasks), names)
        else:
            from dask.multiprocessing import get

            from .pool import process_pool

            context = "fork" if _fork_is_safe() else dask.config.get("multiprocessing.context", "spawn")
            store = open_store(next(iter(tasks.values()))[0].cache_root)
            with process_pool(os.cpu_count() or 1, context, store.drop_tmp_of) as pool:
                values = get(_dask_graph(tasks), names, pool=pool)
    return dict(zip(names, values))


def _fork_is_safe() -> bool:
    """Fork worker processes (fast start, node modules already imported) only on Linux (fork is
    unsafe on macOS) and only while no node has run in this process (OpenMP runtimes do not
    survive a fork)."""
    return sys.platform.startswith("linux") and not _nodes_ran_in_process


def _run_distributed(tasks: dict[str, tuple[TaskSpec, list[str | ArtifactRef]]], order: dict[str, float], address: str,
                     on_done: Done) -> dict[str, TaskResult]:
    import logging

    import dask
    from distributed import Client, LocalCluster, as_completed

    cluster = None
    try:
        if address == "local-cluster":
            # Forked workers start in ~0.15 s and inherit the imported node modules; spawned ones
            # take seconds to re-import everything (see _fork_is_safe).
            method = "fork" if _fork_is_safe() else "spawn"
            from .pool import signals_blocked

            # the workers (and the cluster's threads) keep SIGINT blocked: Ctrl-C stops this process,
            # which closes the cluster, instead of printing a traceback from every worker
            with signals_blocked(), dask.config.set({"distributed.worker.multiprocessing-method": method}):
                cluster = LocalCluster(n_workers=os.cpu_count() or 1, threads_per_worker=1, processes=True,
                                       dashboard_address=None, silence_logs=logging.CRITICAL)
            client = Client(cluster)
        else:
            try:
                client = Client(address, timeout="5s")
            except OSError as exc:
                raise UserError(f"--scheduler {address}: cannot connect to a dask scheduler there ({exc})") from None
        with client:
            names = list(tasks)
            with dask.annotate(priority=order.get):  # the scheduler calls it with each task's name
                futures = client.get(_dask_graph(tasks), names, sync=False)
            by_future = dict(zip(futures, names))
            results: dict[str, TaskResult] = {}
            for future in as_completed(futures):
                try:
                    result = future.result()
                except BaseException:
                    client.cancel(futures)
                    raise
                results[by_future[future]] = result
                on_done(by_future[future], result)
            return results
    finally:
        if cluster is not None:
            cluster.close()
