"""The worker processes of the ``processes`` scheduler: started together, stopped together.

Workers ignore SIGINT (Ctrl-C goes to the whole process group; only the parent reacts, see
:mod:`.interrupts`) and die with the parent: on Linux through ``prctl(PR_SET_PDEATHSIG, SIGKILL)``,
elsewhere by polling their parent pid, so a ``kill -9`` of a run leaves no worker behind. SIGINT is
blocked while the workers are forked (a Ctrl-C at that moment is delivered to the parent just
after, and never reaches a worker before it ignores it). :func:`process_pool` kills the workers on
the way out when the run did not finish, and then removes the cache temp folders they left
(:meth:`.store.Store.drop_tmp_of`).
"""
from __future__ import annotations

import contextlib
import ctypes
import multiprocessing
import os
import signal
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from typing import Callable, Iterator

PR_SET_PDEATHSIG = 1


def _watch_parent(parent_pid: int) -> None:
    while True:
        if os.getppid() != parent_pid:
            os._exit(1)
        time.sleep(0.5)


def _init_worker(parent_pid: int) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
    linked = False
    if sys.platform.startswith("linux"):
        try:
            linked = ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL) == 0
        except (OSError, AttributeError):
            linked = False
    if not linked:
        threading.Thread(target=_watch_parent, args=(parent_pid,), daemon=True).start()
    if os.getppid() != parent_pid:  # the parent died before the link was made
        os._exit(1)


@contextlib.contextmanager
def signals_blocked() -> Iterator[None]:
    """SIGINT/SIGTERM held back in this thread while the block starts child processes and threads:
    they inherit the blocked mask (and never see a Ctrl-C meant for the parent unless they unblock
    it themselves); a signal that came meanwhile is delivered to the parent when the block ends."""
    blocked = {signal.SIGINT, signal.SIGTERM}
    in_main = threading.current_thread() is threading.main_thread()
    if in_main:
        signal.pthread_sigmask(signal.SIG_BLOCK, blocked)
    try:
        yield
    finally:
        if in_main:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, blocked)


@contextlib.contextmanager
def process_pool(workers: int, context: str, on_killed: Callable[[list[int]], None]) -> Iterator[ProcessPoolExecutor]:
    """A started pool of ``workers`` processes; killed (then ``on_killed(pids)``) unless the block
    ends normally, shut down cleanly when it does."""
    with signals_blocked():
        pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context(context),
                                   initializer=_init_worker, initargs=(os.getpid(),))
        for future in [pool.submit(os.getpid) for _ in range(workers)]:
            future.result()  # forked workers all start with the first task
    finished = False
    try:
        yield pool
        finished = True
    finally:
        if finished:
            pool.shutdown(wait=True)
        else:
            on_killed(_kill(pool))


def _kill(pool: ProcessPoolExecutor) -> list[int]:
    """SIGKILL every worker, wait for them, return their pids."""
    processes = list(getattr(pool, "_processes", {}).values())  # no public kill before Python 3.14
    for process in processes:
        with contextlib.suppress(ProcessLookupError, AttributeError):
            process.kill()
    for process in processes:
        process.join(timeout=5)
    manager = getattr(pool, "_executor_manager_thread", None)  # shutdown() forgets it
    pool.shutdown(wait=False, cancel_futures=True)
    if manager is not None:  # it closes its wake-up pipe; interpreter exit must not write to it meanwhile
        manager.join(timeout=5)
    return sorted(p.pid for p in processes)
