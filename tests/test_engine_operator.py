"""The operator's bad days (issue 17): Ctrl-C and kill -9 of a real run, a file or a read-only or
full disk as --out, a full cache disk, damaged cache entries, errors that name the -S behind them,
reproducible manifests. Every case: the right exit code, one stderr line naming the fix, nothing
half-written, no process left behind."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from retrotouch.graph import interrupts
from retrotouch.graph.errors import UserError
from retrotouch.graph.runner import run_pipeline
from retrotouch.graph.store import Store

SLOW = """\
nodes:
  src:  {type: t.source, map: {scale: [1, 2, 3, 4]}, params: {sleep_s: 2}}
  tot:  {type: t.sum, inputs: {xs: "src[*]"}}
  out:  {type: t.write, inputs: {value: tot}}
"""
FAST = """\
nodes:
  src:   {type: t.source, map: {scale: [1, 2, 3]}, params: {n: 3}}
  plus:  {type: t.add, inputs: {x: src}, params: {delta: 10}}
  tot:   {type: t.sum, inputs: {xs: "plus[*]"}}
  out:   {type: t.write, inputs: {value: tot}}
"""
BLOB = "nodes:\n  blob: {type: t.blob, params: {megabytes: 0.1}}\n"


def _process_group(pgid: int) -> list[int]:
    """Live (not zombie) processes of a process group."""
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            fields = stat.rsplit(")", 1)[1].split()
            if int(fields[2]) == pgid and fields[0] != "Z":
                found.append(int(entry))
    return found


def _children(pid: int) -> list[int]:
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _start(tmp_path: Path, text: str, *args: str) -> subprocess.Popen:
    (tmp_path / "p.yaml").write_text(text)
    return subprocess.Popen([sys.executable, "-m", "retrotouch.nodes", "run", "p.yaml", "--out", "out", *args],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def _leftovers(tmp_path: Path) -> list[str]:
    tmp = tmp_path / "cache" / "tmp"
    return sorted(os.listdir(tmp) if tmp.is_dir() else []) + [p.name for p in tmp_path.iterdir() if ".tmp-" in p.name]


def _assert_stopped_cleanly(proc: subprocess.Popen, tmp_path: Path) -> None:
    """The interrupted run printed one line, exited 130 and left no process or temp folder."""
    out, err = proc.communicate(timeout=60)
    assert (proc.returncode, err) == (130, "retrotouch: error: interrupted\n"), out
    deadline = time.time() + 5
    while _process_group(proc.pid) and time.time() < deadline:
        time.sleep(0.05)
    assert _process_group(proc.pid) == []
    assert _leftovers(tmp_path) == []


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc to find the run's processes")
@pytest.mark.parametrize("delay_s", [0.15, 0.8, 1.5, 2.6])
def test_ctrl_c_to_the_process_group_at_any_moment(tmp_path, test_nodes, delay_s):
    """Start-up, pool start, nodes running, the sum: always one line, 130, no process or temp folder left."""
    proc = _start(tmp_path, SLOW)
    try:
        time.sleep(delay_s)
        os.killpg(proc.pid, signal.SIGINT)
        if delay_s == 1.5:  # an impatient operator presses twice
            time.sleep(0.05)
            os.killpg(proc.pid, signal.SIGINT)
        _assert_stopped_cleanly(proc, tmp_path)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert not (tmp_path / "out").exists()
    store = Store(str(tmp_path / "cache"))
    for key, _ in store.entries():
        store.load(store.lookup(key))  # whatever was committed is sound


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc to find the run's processes")
@pytest.mark.parametrize("scheduler", ["local-cluster", "threads", "sync"])
def test_ctrl_c_with_the_other_schedulers(tmp_path, test_nodes, scheduler):
    proc = _start(tmp_path, SLOW, "--scheduler", scheduler)
    try:
        time.sleep(3.0)  # the local cluster's workers are running nodes by then
        os.killpg(proc.pid, signal.SIGINT)
        _assert_stopped_cleanly(proc, tmp_path)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)


def test_sigterm_stops_the_same_way(tmp_path, test_nodes):
    proc = _start(tmp_path, SLOW)
    time.sleep(1.0)
    os.killpg(proc.pid, signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert (proc.returncode, err) == (143, "retrotouch: error: interrupted\n")
    assert _leftovers(tmp_path) == []


def _swallow_a_ctrl_c() -> None:
    """What trimesh's optional-import guards do with an interruption that lands in them."""
    try:
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(1.0)  # the handler runs here
    except BaseException:  # noqa: BLE001 - the library's, on purpose
        pass


def test_an_interruption_a_library_swallows_is_raised_again_by_check():
    previous = interrupts.install()
    try:
        _swallow_a_ctrl_c()
        assert interrupts.requested().signum == signal.SIGINT
        with pytest.raises(interrupts.Interrupted):
            interrupts.check()
    finally:
        interrupts.restore(previous)
    assert interrupts.requested() is None


def test_an_error_after_a_swallowed_interruption_is_reported_as_the_interruption(monkeypatch, capsys):
    """A C extension cut short in its initialisation raises ImportError('initialization failed')."""
    from retrotouch.graph.cli import main
    from retrotouch.nodes.app import APP
    from retrotouch.nodes.sensing import cli as sensing_cli

    def start_up(**_):
        _swallow_a_ctrl_c()
        raise ImportError("initialization failed")

    monkeypatch.setattr(sensing_cli, "_sense", start_up)
    with pytest.raises(SystemExit) as stopped:
        main(APP, ["sense", "--simulate"])
    assert stopped.value.code == 130
    assert capsys.readouterr().err == "retrotouch: error: interrupted\n"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc to find the workers")
def test_kill_9_of_a_run_leaves_no_worker(tmp_path, test_nodes):
    proc = _start(tmp_path, SLOW)
    try:
        deadline = time.time() + 30
        while len(_children(proc.pid)) < 2 and time.time() < deadline:
            time.sleep(0.05)
        workers = _children(proc.pid)
        assert len(workers) >= 2, "the run never started its worker processes"
        proc.kill()
        proc.communicate(timeout=30)
        deadline = time.time() + 5
        while any(map(_alive, workers)) and time.time() < deadline:
            time.sleep(0.05)
        assert [w for w in workers if _alive(w)] == []
    finally:
        with_group = _process_group(proc.pid)
        for pid in with_group:
            os.kill(pid, signal.SIGKILL)


def test_out_naming_a_file_is_refused_before_anything_runs(tmp_path, cli, test_nodes):
    (tmp_path / "p.yaml").write_text(FAST)
    (tmp_path / "notes.txt").write_text("precious")
    result = cli("run", "p.yaml", "--out", "notes.txt")
    assert result.returncode == 2
    assert result.stderr == f"retrotouch: error: --out {tmp_path / 'notes.txt'} is a file, not a folder; choose " \
                            "another --out (a new folder or a previous output folder)\n"
    assert (tmp_path / "notes.txt").read_text() == "precious"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache", "notes.txt", "p.yaml"] or \
        sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt", "p.yaml"]
    assert Store(str(tmp_path / "cache")).entries() == []  # no node ran


@pytest.fixture
def tmpfs(tmp_path):
    """``mount(size, read_only=False)``: a small tmpfs under tmp_path (root only), unmounted after."""
    mounted: list[Path] = []

    def mount(size: str, read_only: bool = False) -> Path:
        if os.geteuid() != 0:
            pytest.skip("mounting a small or read-only filesystem needs root")
        where = tmp_path / f"fs{len(mounted)}"
        where.mkdir()
        options = f"size={size}" + (",ro" if read_only else "")
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(where)], capture_output=True,
                              text=True, timeout=30)
        if done.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
        mounted.append(where)
        return where

    yield mount
    for where in mounted:
        subprocess.run(["umount", "-l", str(where)], capture_output=True, timeout=30)


def test_read_only_out_and_cache_are_refused_before_anything_runs(tmp_path, cli, test_nodes, tmpfs):
    (tmp_path / "p.yaml").write_text(FAST)
    read_only = tmpfs("4m", read_only=True)
    result = cli("run", "p.yaml", "--out", str(read_only / "out"))
    assert result.returncode == 2
    assert result.stderr == f"retrotouch: error: --out {read_only / 'out'} is not writable (Read-only file system); " \
                            "choose another --out\n"
    assert Store(str(tmp_path / "cache")).entries() == []
    result = cli("run", "p.yaml", "--out", "out", "--cache-dir", str(read_only / "cache"))
    assert result.returncode == 2 and result.stderr.count("\n") == 1
    assert f"cache {read_only / 'cache'} is not writable (Read-only file system); pass --cache-dir" in result.stderr
    assert not (tmp_path / "out").exists()


def test_full_out_disk_is_found_before_anything_runs(tmp_path, cli, test_nodes, tmpfs):
    (tmp_path / "p.yaml").write_text(FAST)
    small = tmpfs("2m")
    result = cli("run", "p.yaml", "--out", str(small / "out"))
    assert result.returncode == 2 and result.stderr.count("\n") == 1
    assert result.stderr.startswith(f"retrotouch: error: --out {small / 'out'}: only 2.1 MB free on its disk")
    assert result.stderr.endswith("free some space or choose another --out\n")
    assert Store(str(tmp_path / "cache")).entries() == []


def test_disks_filling_up_during_the_run_are_one_line_and_leave_the_last_output(tmp_path, cli, test_nodes, tmpfs):
    """Enough room at the start, not for what the run writes (80 MB): the previous output folder
    stays as it was, and no temp folder is left on either disk."""
    (tmp_path / "p.yaml").write_text(BLOB)
    out_disk = tmpfs("72m")
    assert cli("run", "p.yaml", "--out", str(out_disk / "out")).returncode == 0
    before = (out_disk / "out" / "manifest.json").read_text()
    result = cli("run", "p.yaml", "--out", str(out_disk / "out"), "-S", "blob.megabytes=80")
    assert result.returncode == 2, result.stderr
    assert result.stderr == f"retrotouch: error: --out {out_disk / 'out'}: no space left on the device; free some " \
                            "space or choose another --out\n"
    assert (out_disk / "out" / "manifest.json").read_text() == before
    assert sorted(os.listdir(out_disk)) == ["out"]
    cache_disk = tmpfs("72m")
    result = cli("run", "p.yaml", "--out", "out2", "--cache-dir", str(cache_disk), "-S", "blob.megabytes=80")
    assert result.returncode == 2, result.stderr
    assert result.stderr == f"retrotouch: error: cache {cache_disk}: no space left on the device; free some space " \
                            "or pass --cache-dir on another disk\n"
    assert os.listdir(cache_disk / "tmp") == [] and not (tmp_path / "out2").exists()


def _flip_bytes(folder: str, suffix: str) -> None:
    """Damage an entry's file without changing its size (bit rot, a bad copy)."""
    victim = next(Path(folder).glob(f"*{suffix}"))
    data = bytearray(victim.read_bytes())
    data[-1] ^= 0xFF
    victim.write_bytes(bytes(data))


def test_damaged_entries_are_deleted_and_recomputed_in_the_same_run(tmp_path, test_nodes):
    (tmp_path / "p.yaml").write_text(FAST)
    kw = dict(out_dir=str(tmp_path / "out"), cache_dir=str(tmp_path / "cache"), scheduler="sync")
    first = run_pipeline(str(tmp_path / "p.yaml"), **kw)
    store = Store(str(tmp_path / "cache"))
    keys = {i.id: i.key for i in first.plan.instances}
    _flip_bytes(store.entry_dir(keys["src[scale=2]"]), ".npy")  # read by plus when it reruns
    _flip_bytes(store.entry_dir(keys["out"]), ".bin")  # read when the output folder is written
    again = run_pipeline(str(tmp_path / "p.yaml"), ["plus.delta=11"], **kw)
    assert sorted(again.ran()) == sorted(["src[scale=2]", "plus[scale=1]", "plus[scale=2]", "plus[scale=3]", "tot", "out"])
    assert len(again.repaired) == 1 and "does not match its recorded sha256" in again.repaired[0]
    assert json.loads((tmp_path / "out" / "value.json").read_text()) == 3 * (1 + 2 + 3) + 3 * 3 * 11
    restored = run_pipeline(str(tmp_path / "p.yaml"), **kw)  # back to delta=10: only `out` was damaged there
    assert restored.ran() == ["out"] and len(restored.repaired) == 1
    assert json.loads((tmp_path / "out" / "value.json").read_text()) == 3 * (1 + 2 + 3) + 3 * 3 * 10


def test_cache_gc_finds_entries_whose_content_no_longer_matches(tmp_path, cli, test_nodes):
    (tmp_path / "p.yaml").write_text(FAST)
    assert cli("run", "p.yaml", "--out", "out").returncode == 0
    store = Store(str(tmp_path / "cache"))
    assert len(store.entries()) == 8
    _flip_bytes(store.entries()[0][1], "value.json")
    result = cli("cache", "gc")
    assert result.returncode == 0 and "1 corrupt entries" in result.stdout
    assert len(store.entries()) == 7


def test_errors_from_overrides_name_the_override(tmp_path, test_nodes):
    text = "params:\n  n_values: 3\nnodes:\n  src: {type: t.source, params: {n: \"${n_values}\"}}\n"
    (tmp_path / "p.yaml").write_text(text)
    kw = dict(out_dir=str(tmp_path / "out"), cache_dir=str(tmp_path / "cache"), scheduler="sync")
    with pytest.raises(UserError) as info:
        run_pipeline(str(tmp_path / "p.yaml"), ["n_values=-5"], **kw)
    assert str(info.value) == f"-S n_values=-5 (used at {tmp_path / 'p.yaml'}:4:37): node 'src' (t.source): " \
                              "param 'n': Input should be greater than or equal to 1 (got -5)"
    with pytest.raises(UserError) as info:  # an override of the node param itself: named, no site
        run_pipeline(str(tmp_path / "p.yaml"), ["src.n=0"], **kw)
    assert str(info.value).startswith("-S src.n=0: node 'src' (t.source): param 'n': ")


def test_a_params_model_validator_is_reported_without_an_empty_param_name(tmp_path, test_nodes):
    (tmp_path / "p.yaml").write_text("nodes:\n  r: {type: t.range, params: {low: 2, high: 1}}\n")
    with pytest.raises(UserError) as info:
        run_pipeline(str(tmp_path / "p.yaml"), out_dir=str(tmp_path / "out"), cache_dir=str(tmp_path / "cache"))
    assert str(info.value) == f"{tmp_path / 'p.yaml'}:2:30: node 'r' (t.range): params: high must be above low"
    (tmp_path / "q.yaml").write_text("nodes:\n  r: {type: t.range, params: {low: 0, high: 1}}\n")
    with pytest.raises(UserError) as info:  # the params are fine in the file: the override is named
        run_pipeline(str(tmp_path / "q.yaml"), ["r.low=3"], out_dir=str(tmp_path / "out"), cache_dir=str(tmp_path / "cache"))
    assert str(info.value) == "-S r.low=3: node 'r' (t.range): params: high must be above low"


def test_source_date_epoch_fixes_the_manifest_time(tmp_path, test_nodes, monkeypatch):
    (tmp_path / "p.yaml").write_text(FAST)
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    kw = dict(cache_dir=str(tmp_path / "cache"), scheduler="sync")
    first = run_pipeline(str(tmp_path / "p.yaml"), out_dir=str(tmp_path / "a"), **kw)
    assert first.manifest["created"] == "2023-11-14T22:13:20Z"
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "yesterday")
    with pytest.raises(UserError, match="SOURCE_DATE_EPOCH='yesterday' is not a whole number"):
        run_pipeline(str(tmp_path / "p.yaml"), out_dir=str(tmp_path / "b"), **kw)
