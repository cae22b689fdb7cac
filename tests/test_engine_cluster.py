"""A real cluster (issue 16 item 5): a `dask scheduler` and two `dask worker` processes started as
on separate machines (own working folder, own local state), and a cache on object storage through
fsspec (memory:// in one process; s3:// against a moto S3 server on 127.0.0.1) so that workers need
no shared filesystem. Keys, atomic commits and damaged-entry detection hold there too."""
from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from retrotouch.graph.runner import run_pipeline
from retrotouch.graph.store import open_store

SWEEP = """\
nodes:
  src:   {type: t.source, map: {scale: [1, 2, 3]}, params: {n: 3}}
  plus:  {type: t.add, inputs: {x: src}, params: {delta: 10}}
  tot:   {type: t.sum, inputs: {xs: "plus[*]"}}
  out:   {type: t.write, inputs: {value: tot}}
  pids:  {type: t.pid, map: {branch: [0, 1, 2, 3]}, params: {sleep_s: 0.6}}
  who:   {type: t.write, inputs: {value: pids}, params: {filename: pid.json}}
"""
TOTAL = 3 * (1 + 2 + 3) + 3 * 3 * 10


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_port(port: int, proc: subprocess.Popen, timeout: float = 60) -> None:
    deadline = time.time() + timeout
    while time.time() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"server exited with {proc.returncode} (see {proc.args})")
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=0.5):
            return
        time.sleep(0.1)
    raise TimeoutError(f"nothing listens on 127.0.0.1:{port} after {timeout} s")


@contextlib.contextmanager
def _processes(logs: Path, name: str):
    """Start processes in their own sessions (output to log files in ``logs``, never an unread
    pipe that would fill and block them); on the way out stop each one's group by its id."""
    started: list[subprocess.Popen] = []

    def start(args: list[str], **kw) -> subprocess.Popen:
        with open(logs / f"{name}{len(started)}.log", "w") as log:
            proc = subprocess.Popen(args, start_new_session=True, stdout=log, stderr=subprocess.STDOUT, **kw)
        started.append(proc)
        return proc

    try:
        yield start
    finally:
        for proc in started:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGTERM)
        for proc in started:
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=10)


@pytest.fixture
def s3(tmp_path, monkeypatch):
    """A moto S3 server on 127.0.0.1; the environment points fsspec's s3:// at it."""
    pytest.importorskip("moto.server", reason="moto[server] is not installed (pip install 'moto[server]')")
    pytest.importorskip("s3fs", reason="s3fs is not installed")
    port = _free_port()
    with _processes(tmp_path, "s3-server") as start:
        server = start([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)])
        _wait_port(port, server)
        endpoint = f"http://127.0.0.1:{port}"
        for name, value in {"FSSPEC_S3_ENDPOINT_URL": endpoint, "AWS_ACCESS_KEY_ID": "testing",
                            "AWS_SECRET_ACCESS_KEY": "testing", "AWS_DEFAULT_REGION": "us-east-1"}.items():
            monkeypatch.setenv(name, value)
        monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "client-local"))
        import fsspec.config

        # this process imported fsspec before the variables were set: configure it directly
        monkeypatch.setitem(fsspec.config.conf, "s3", {"endpoint_url": endpoint})
        yield endpoint


@pytest.fixture
def cluster(tmp_path, test_nodes):
    """``dask scheduler`` and two ``dask worker`` processes on 127.0.0.1, each worker in its own folder
    with its own local state (XDG_CACHE_HOME), as on separate machines; yields the scheduler address."""
    from distributed import Client

    scheduler_file = tmp_path / "scheduler.json"
    with _processes(tmp_path, "dask") as start:
        start([sys.executable, "-m", "dask", "scheduler", "--host", "127.0.0.1", "--port", "0",
               "--no-dashboard", "--scheduler-file", str(scheduler_file)], cwd=tmp_path)
        deadline = time.time() + 60
        while not scheduler_file.exists() and time.time() < deadline:
            time.sleep(0.1)
        for k in range(2):
            machine = tmp_path / f"machine{k}"
            machine.mkdir()
            env = {**os.environ, "XDG_CACHE_HOME": str(machine / "local")}
            start([sys.executable, "-m", "dask", "worker", "--scheduler-file", str(scheduler_file), "--nthreads", "1",
                   "--host", "127.0.0.1", "--no-dashboard", "--local-directory", str(machine / "dask")],
                  cwd=machine, env=env)
        address = json.loads(scheduler_file.read_text())["address"]
        with Client(address, timeout="30s") as client:
            client.wait_for_workers(2, timeout=90)
            worker_pids = set(client.run(os.getpid).values())
        yield address, worker_pids


def _run(cli, *args: str):
    result = cli("run", "p.yaml", "--out", "out", "--json", *args, timeout=300)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def test_pipeline_on_a_dask_scheduler_and_two_worker_processes(tmp_path, cli, cluster):
    address, worker_pids = cluster
    (tmp_path / "p.yaml").write_text(SWEEP)
    summary = _run(cli, "--scheduler", address)
    assert summary["ran"] == 3 * 2 + 2 + 4 + 4
    assert json.loads((tmp_path / "out" / "value.json").read_text()) == TOTAL
    ran_on = {json.loads((tmp_path / "out" / f"branch={b}" / "pid.json").read_text()) for b in range(4)}
    assert ran_on == worker_pids and len(worker_pids) == 2  # both workers took branches, the client none
    assert _run(cli, "--scheduler", address)["ran"] == 0


def _s3_files(store, folder: str) -> list[str]:
    return [p for p in store.fs.find(folder) if not p.endswith("meta.json")]


def test_s3_cache_shared_by_workers_with_no_common_filesystem(tmp_path, cli, s3, cluster):
    address, worker_pids = cluster
    (tmp_path / "p.yaml").write_text(SWEEP)
    url = "s3://retrotouch-cache/team/run-cache"
    first = _run(cli, "--scheduler", address, "--cache-dir", url)
    assert first["ran"] == 16 and json.loads((tmp_path / "out" / "value.json").read_text()) == TOTAL
    assert not (tmp_path / "cache").exists() and not list(tmp_path.glob("machine*/cache"))
    store = open_store(url)
    entries = store.entries()
    assert sorted(k for k, _ in entries) == sorted(n["key"] for n in first["nodes"])
    for key, folder in entries:  # one complete commit per key, every sha256 right
        meta = store.verify(folder, key)
        assert sorted(store._ls(folder)) == sorted([meta["commit"], "meta.json"])
    assert _run(cli, "--scheduler", address, "--cache-dir", url)["ran"] == 0
    # bit rot in the object store, same size: found when read, deleted, recomputed in the same run
    victim = next(n["key"] for n in first["nodes"] if n["id"] == "src[scale=2]")
    path = next(p for p in _s3_files(store, store.entry_dir(victim)) if p.endswith(".npy"))
    data = bytearray(store.fs.cat_file(path))
    data[-1] ^= 0xFF
    store.fs.pipe_file(path, bytes(data))
    again = _run(cli, "--scheduler", address, "--cache-dir", url, "-S", "plus.delta=11")
    assert "src[scale=2]" in [n["id"] for n in again["nodes"] if n["status"] == "ran"]
    assert len(again["repaired"]) == 1
    assert json.loads((tmp_path / "out" / "value.json").read_text()) == TOTAL + 3 * 3


def test_memory_cache_in_one_process(tmp_path, test_nodes, monkeypatch):
    from retrotouch.graph import maintenance
    from retrotouch.graph.errors import UserError

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "local"))
    (tmp_path / "p.yaml").write_text(SWEEP.replace("sleep_s: 0.6", "sleep_s: 0"))
    url = f"memory://rt-{os.getpid()}-{time.time_ns()}/cache"
    kw = dict(out_dir=str(tmp_path / "out"), cache_dir=url)
    first = run_pipeline(str(tmp_path / "p.yaml"), scheduler="threads", **kw)
    assert len(first.ran()) == 16 and json.loads((tmp_path / "out" / "value.json").read_text()) == TOTAL
    assert run_pipeline(str(tmp_path / "p.yaml"), **kw).ran() == []  # auto: in this process
    store = open_store(url)
    victim = next(i.key for i in first.plan.instances if i.id == "out")
    path = next(p for p in _s3_files(store, store.entry_dir(victim)) if p.endswith(".bin"))
    store.fs.pipe_file(path, b"[0]" + store.fs.cat_file(path)[3:])
    repaired = run_pipeline(str(tmp_path / "p.yaml"), **kw)
    assert repaired.ran() == ["out"] and json.loads((tmp_path / "out" / "value.json").read_text()) == TOTAL
    other = next(i.key for i in first.plan.instances if i.id == "tot")
    path = next(p for p in _s3_files(store, store.entry_dir(other)))
    store.fs.pipe_file(path, bytes(len(store.fs.cat_file(path))))
    assert "1 corrupt entries" in maintenance.gc(store, None, None)[0]
    assert len(store.entries()) == 15
    # a losing writer's commit beside a sound one, and a writer still uploading (no meta.json yet)
    sound_key, sound = store.entries()[0]
    store.fs.pipe_file(f"{sound}/0123abcd/value.json", b"{}")
    uploading = store.entry_dir("ff" + "0" * 62)
    store.fs.pipe_file(f"{uploading}/4567cdef/value.json", b"{}")
    assert "0 stale temp dirs, 0 corrupt entries" in maintenance.gc(store, None, None)[0]  # both too young
    assert len(store.entries()) == 16
    monkeypatch.setattr(maintenance, "STALE_TMP_SECONDS", 0.0)
    assert "1 stale temp dirs, 1 corrupt entries" in maintenance.gc(store, None, None)[0]
    assert store._ls(sound) == sorted([store.read_meta(sound, sound_key)["commit"], "meta.json"])
    assert len(store.entries()) == 15
    with pytest.raises(UserError, match="lives in this process only"):
        run_pipeline(str(tmp_path / "p.yaml"), ["plus.delta=1"], scheduler="processes", **kw)


def test_concurrent_writers_of_one_key_on_object_storage_leave_one_sound_entry(tmp_path, monkeypatch):
    import threading

    import numpy as np

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "local"))
    store = open_store(f"memory://rt-{os.getpid()}-{time.time_ns()}/race")
    key = "ab" + "1" * 62
    barrier = threading.Barrier(8)

    def write(i: int) -> None:
        barrier.wait()
        store.write(key, {"values": np.full(50_000, i, dtype=np.int64), "who": i}, info={})

    threads = [threading.Thread(target=write, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    value = store.load(store.lookup(key))
    assert set(np.unique(value["values"])) == {value["who"]}  # one writer's complete value, never a mix
    meta = store.verify(store.entry_dir(key), key)
    assert meta["commit"] in store._ls(store.entry_dir(key))
