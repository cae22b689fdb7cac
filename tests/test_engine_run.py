"""Running pipelines: exactly the right nodes rerun, failures are one line, runs share a cache safely,
the default pipeline works end to end, and a dask.distributed cluster can execute the work."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from retrotouch.graph.errors import UserError
from retrotouch.graph.runner import run_pipeline
from retrotouch.graph.store import Store

SWEEP = """\
params:
  scales: [1, 2, 3]
nodes:
  src:   {type: t.source, map: {scale: "${scales}"}, params: {n: 3}}
  plus:  {type: t.add, inputs: {x: src}, params: {delta: 10}}
  stats: {type: t.stats, inputs: {x: plus}}
  tot:   {type: t.sum, inputs: {xs: "plus[*]"}}
  out:   {type: t.write, inputs: {value: tot}}
  means: {type: t.write, inputs: {value: stats.mean}, params: {filename: mean.json}}
"""
# sum over scales s of (0 + 1 + 2) * s + 3 * 10
SWEEP_TOTAL = 3 * (1 + 2 + 3) + 3 * 3 * 10


def pipeline_file(tmp_path: Path, text: str = SWEEP) -> str:
    path = tmp_path / "sweep.yaml"
    path.write_text(text)
    return str(path)


def run(tmp_path, overrides=(), **kw):
    return run_pipeline(pipeline_file(tmp_path), list(overrides), out_dir=str(tmp_path / "out"),
                        cache_dir=str(tmp_path / "cache"), scheduler=kw.pop("scheduler", "sync"), **kw)


def test_values_fan_in_and_branch_outputs(tmp_path, test_nodes):
    result = run(tmp_path)
    assert json.loads((tmp_path / "out" / "value.json").read_text()) == SWEEP_TOTAL
    assert json.loads((tmp_path / "out" / "scale=2" / "mean.json").read_text()) == 2 * 1 + 10
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert sorted(manifest["files"]) == ["scale=1/mean.json", "scale=2/mean.json", "scale=3/mean.json", "value.json"]
    assert len(result.ran()) == 3 * 4 + 2


def test_param_change_reruns_exactly_that_node_and_its_descendants(tmp_path, test_nodes):
    run(tmp_path)
    again = run(tmp_path)
    assert again.ran() == []
    changed = run(tmp_path, ["plus.delta=20"], explain=True)
    assert changed.ran() == ["plus[scale=1]", "plus[scale=2]", "plus[scale=3]", "stats[scale=1]", "stats[scale=2]",
                             "stats[scale=3]", "tot", "out", "means[scale=1]", "means[scale=2]", "means[scale=3]"]
    reasons = {i.id: i.reason for i in changed.plan.to_run}
    assert reasons["plus[scale=1]"] == "params changed: delta"
    assert reasons["tot"] == "inputs changed: xs"
    assert json.loads((tmp_path / "out" / "value.json").read_text()) == SWEEP_TOTAL + 3 * 3 * 10


def test_cache_modes(tmp_path, test_nodes):
    text = SWEEP.replace("params: {delta: 10}}", "params: {delta: 10}, cache: disable}") \
                .replace("inputs: {xs: \"plus[*]\"}}", "inputs: {xs: \"plus[*]\"}, cache: recompute}")
    path = pipeline_file(tmp_path, text)
    kw = dict(out_dir=str(tmp_path / "out"), cache_dir=str(tmp_path / "cache"), scheduler="sync")
    run_pipeline(path, **kw)
    second = run_pipeline(path, **kw)
    # disable: plus is never stored, so it runs again only because the recomputed tot needs it
    assert second.ran() == ["plus[scale=1]", "plus[scale=2]", "plus[scale=3]", "tot"]
    keys = {k for k, _ in Store(str(tmp_path / "cache")).entries()}
    assert not any(i.key in keys for i in second.plan.instances if i.node == "plus")
    assert not os.listdir(tmp_path / "cache" / "scratch")


def test_damaged_cache_entry_is_recomputed_not_read(tmp_path, test_nodes):
    first = run(tmp_path)
    victim = next(i for i in first.plan.instances if i.id == "plus[scale=2]")
    folder = Store(str(tmp_path / "cache")).entry_dir(victim.key)
    npy = next(Path(folder).glob("*.npy"))
    npy.write_bytes(npy.read_bytes()[:40])  # a writer killed half-way through this file
    again = run(tmp_path)
    assert again.ran() == ["plus[scale=2]"]
    assert json.loads((tmp_path / "out" / "value.json").read_text()) == SWEEP_TOTAL


def test_threads_and_processes_schedulers_agree(tmp_path, test_nodes):
    for scheduler in ("threads", "processes"):
        result = run(tmp_path / scheduler, scheduler=scheduler) if (tmp_path / scheduler).mkdir() is None else None
        assert len(result.ran()) == 14
        assert json.loads((tmp_path / scheduler / "out" / "value.json").read_text()) == SWEEP_TOTAL


def test_node_errors_are_one_line(tmp_path, cli, test_nodes):
    text = "nodes:\n  src: {type: t.source}\n  bad: {type: t.fail, inputs: {x: src}, params: {kind: user}}\n"
    (tmp_path / "p.yaml").write_text(text)
    result = cli("run", "p.yaml", "--scheduler", "sync")
    assert result.returncode == 2
    assert result.stderr.strip() == "retrotouch: error: node bad: the input is unusable; pick another one"
    # on a dask.distributed LocalCluster, whose worker logs must not add lines
    result = cli("run", "p.yaml", "-S", "bad.kind=crash", "-S", "nodes.src.map={scale: [1, 2]}",
                 "--scheduler", "local-cluster")
    assert result.returncode == 1
    line = result.stderr.strip()
    assert re.match(r"retrotouch: error: node bad\[scale=[12]\] failed: ZeroDivisionError", line) and "\n" not in line
    log = line.split("(traceback: ")[1].rstrip(")")
    assert "Traceback" in Path(log).read_text() and "Traceback" not in result.stderr
    assert cli("run", "p.yaml", "--scheduler", "fast").returncode == 2
    result = cli("run", "p.yaml", "-S", "nodes.src.map={scale: [1, 2]}")  # auto: forked process pool
    assert result.returncode == 2 and re.fullmatch(r"retrotouch: error: node bad\[scale=[12]\]: the input is "
                                                   r"unusable; pick another one\n", result.stderr)


def test_out_dir_not_written_by_retrotouch_is_refused(tmp_path, test_nodes):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "thesis.tex").write_text("precious")
    with pytest.raises(UserError, match="was not written by retrotouch"):
        run(tmp_path)
    assert (tmp_path / "out" / "thesis.tex").read_text() == "precious"


CODE_V1 = '''
from pydantic import Field
from retrotouch.graph.node import NodeParams, node


class P(NodeParams):
    x: float = Field(1.0)


@node("cv.value", params=P, outputs=("value",))
def value(params: P) -> float:
    """Doc."""
    return params.x * 2
'''


def test_code_change_invalidates_but_comments_do_not(tmp_path, cli, test_nodes):
    (tmp_path / "rt_cvnodes.py").write_text(CODE_V1)
    (tmp_path / "p.yaml").write_text("nodes:\n  v: {type: cv.value}\n  w: {type: t.write, inputs: {value: v}}\n")
    env = {"PYTHONPATH": f"{tmp_path}{os.pathsep}{os.environ['PYTHONPATH']}", "PYTHONDONTWRITEBYTECODE": "1",
           "RETROTOUCH_NODE_MODULES": "rt_testnodes,rt_cvnodes"}

    def ran():
        result = cli("run", "p.yaml", "--out", "out", "--scheduler", "sync", env=env)
        assert result.returncode == 0, result.stderr
        manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
        return [n["node"] for n in manifest["nodes"] if n["status"] == "ran"], json.loads(
            (tmp_path / "out" / "value.json").read_text())

    assert ran() == (["v", "w"], 2.0)
    (tmp_path / "rt_cvnodes.py").write_text(CODE_V1.replace('"""Doc."""', "# only a comment now"))
    assert ran() == ([], 2.0)
    (tmp_path / "rt_cvnodes.py").write_text(CODE_V1.replace("params.x * 2", "params.x * 3"))
    assert ran() == (["v", "w"], 3.0)


def test_two_concurrent_runs_share_one_cache(tmp_path, cli, test_nodes):
    (tmp_path / "p.yaml").write_text(SWEEP.replace("params: {n: 3}", "params: {n: 3, sleep_s: 0.3}"))
    env = {**os.environ}
    procs = [subprocess.Popen([sys.executable, "-m", "retrotouch.nodes", "run", "p.yaml", "--scheduler", "sync",
                               "--out", f"out{k}", "--cache-dir", "cache"], cwd=tmp_path, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for k in range(2)]
    outputs = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outputs
    manifests = [json.loads((tmp_path / f"out{k}" / "manifest.json").read_text()) for k in range(2)]
    assert manifests[0]["files"] == manifests[1]["files"]
    ran = [sum(n["status"] == "ran" for n in m["nodes"]) for m in manifests]
    assert sum(ran) == 14  # every key computed exactly once between the two runs
    store = Store(str(tmp_path / "cache"))
    for key, folder in store.entries():
        store.load(store.lookup(key))  # every entry sound (sha256 checked)
    assert len(store.entries()) == 14
    assert json.loads((tmp_path / "out0" / "value.json").read_text()) == SWEEP_TOTAL


def test_default_pipeline_end_to_end(repo, default_run, cli):
    """The README's main job: every output of the full pipeline, then a warm rerun and a downstream tweak."""
    pipeline = repo / "pipelines" / "retrofit.yaml"
    out = default_run / "out"
    manifest = json.loads((out / "manifest.json").read_text())
    import hashlib

    for name in ("mesh.ply", "sensing_map.json", "metrics.json", "preview.png", "preview.html",
                 "sheets/sheet_1.svg", "sheets/sheet_1.pdf", "sheets/sheet_1.dxf", "assembly_guide.pdf",
                 "projection/bunny_layout.glb", "projection/bunny_layout.obj"):
        assert manifest["files"][name]["sha256"] == hashlib.sha256((out / name).read_bytes()).hexdigest(), name
    assert manifest["pipeline"]["sha256"] == hashlib.sha256(pipeline.read_bytes()).hexdigest()
    assert all(n["status"] == "ran" for n in manifest["nodes"])
    assert sum(n["node"] == "select" for n in manifest["nodes"]) == 0  # the dipole loops: off unless rx_angles_deg lists angles
    assert sum(n["node"] == "ring_select" for n in manifest["nodes"]) == 0  # the rings: in the fallback's sweep only
    assert sum(n["node"] == "helix_select" for n in manifest["nodes"]) == 4  # one per winding sense and climb
    assert sum(n["node"] == "grid_select" for n in manifest["nodes"]) == 4  # geodesic or plan, lines across or along as Tx
    metrics = json.loads((out / "metrics.json").read_text())
    assert len(metrics["angles"]) == 8
    assert {row["rx_family"] for row in metrics["angles"]} == {"helices", "helices_per_line", "grid", "grid_plan"}
    fallback = manifest["fallback"]  # the pipeline's second sweep (the other Tx poles, the rings) reads the chosen layout's metric
    assert fallback["value"] == "best.metrics.uncovered_share" and fallback["read"] == metrics["uncovered_share"] < 0.2
    assert not fallback["ran_again"] and manifest["overrides"] == []

    ply = (out / "mesh.ply").read_bytes()
    assert ply.startswith(b"ply\nformat binary_little_endian 1.0\n")
    sensing_map = json.loads((out / "sensing_map.json").read_text())
    assert sensing_map["mesh"]["sha256"] == hashlib.sha256(ply).hexdigest()
    assert sensing_map["tx_channels"] <= 21 and sensing_map["rx_channels"] <= 12
    assert len({(c["tx"], c["rx"]) for c in sensing_map["cells"]}) == len(sensing_map["cells"]) > 50
    import trimesh

    mesh = trimesh.load(out / "mesh.ply", process=False)
    diagonal = float(((mesh.bounds[1] - mesh.bounds[0]) ** 2).sum() ** 0.5)
    assert diagonal == pytest.approx(170, rel=0.02)  # remeshing moves the surface a little

    again = cli("run", pipeline, "--out", "out", cwd=default_run)
    assert again.returncode == 0 and "0 ran," in again.stdout
    downstream = cli("run", pipeline, "--out", "out", "-S", "nest.nester=shelf", cwd=default_run)
    assert downstream.returncode == 0, downstream.stderr
    manifest = json.loads((out / "manifest.json").read_text())
    assert sorted(n["node"] for n in manifest["nodes"] if n["status"] == "ran") == ["nest", "sheets"]
    assert manifest["overrides"] == ["nest.nester=shelf"]


def test_run_on_a_dask_distributed_cluster(tmp_path, cli, test_nodes):
    from distributed import LocalCluster

    (tmp_path / "p.yaml").write_text(SWEEP)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        result = cli("run", "p.yaml", "--scheduler", cluster.scheduler_address, "--out", "out")
        assert result.returncode == 0, result.stderr
    assert json.loads((tmp_path / "out" / "value.json").read_text()) == SWEEP_TOTAL
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert manifest["scheduler"].startswith("tcp://")
    assert sum(n["status"] == "ran" for n in manifest["nodes"]) == 14
    bad = cli("run", "p.yaml", "--scheduler", "tcp://127.0.0.1:9", "-S", "plus.delta=99")
    assert bad.returncode == 2 and "cannot connect" in bad.stderr and bad.stderr.count("\n") == 1


def test_unchanged_rerun_skips_planning_but_notices_changes(tmp_path, test_nodes):
    from retrotouch.graph.plan import Plan
    from retrotouch.graph.snapshot import SnapshotPlan

    first = run(tmp_path)
    assert isinstance(first.plan, Plan)
    again = run(tmp_path)
    assert isinstance(again.plan, SnapshotPlan) and again.ran() == []
    assert [n["key"] for n in again.manifest["nodes"]] == [n["key"] for n in first.manifest["nodes"]]
    assert again.manifest["nodes"][1]["params"] == first.manifest["nodes"][1]["params"]
    assert json.loads((tmp_path / "out" / "value.json").read_text()) == SWEEP_TOTAL
    # an override, an edited pipeline and a deleted entry all fall back to full planning
    assert isinstance(run(tmp_path, ["plus.delta=11"]).plan, Plan)
    victim = first.plan.instances[-1]
    Store(str(tmp_path / "cache")).discard(Store(str(tmp_path / "cache")).entry_dir(victim.key))
    rerun = run(tmp_path)
    assert isinstance(rerun.plan, Plan) and rerun.ran() == [victim.id]
    (tmp_path / "sweep.yaml").write_text(SWEEP.replace("delta: 10", "delta: 12"))
    edited = run_pipeline(str(tmp_path / "sweep.yaml"), out_dir=str(tmp_path / "out"),
                          cache_dir=str(tmp_path / "cache"), scheduler="sync")
    assert isinstance(edited.plan, Plan) and "tot" in edited.ran()


def test_runs_replacing_the_same_output_folder_at_once(tmp_path, test_nodes):
    import threading

    run(tmp_path)
    errors = []

    def again():  # the same pipeline file, not rewritten by each thread as run() does
        try:
            run_pipeline(str(tmp_path / "sweep.yaml"), out_dir=str(tmp_path / "out"), cache_dir=str(tmp_path / "cache"),
                         scheduler="sync")
        except Exception as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=again) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["manifest.json", "scale=1", "scale=2", "scale=3",
                                                                   "value.json"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.tmp")]


def test_processes_scheduler_from_the_cli(tmp_path, cli, test_nodes):
    (tmp_path / "p.yaml").write_text(SWEEP)
    result = cli("run", "p.yaml", "--scheduler", "processes", "--out", "out")
    assert result.returncode == 0, result.stderr
    assert json.loads((tmp_path / "out" / "value.json").read_text()) == SWEEP_TOTAL


def test_a_reduce_over_two_mapped_nodes_sums_both(tmp_path, test_nodes):
    text = SWEEP.replace('tot:   {type: t.sum, inputs: {xs: "plus[*]"}}',
                         'more:  {type: t.add, inputs: {x: src}, map: {delta: [100, 200]}}\n'
                         '  tot:   {type: t.sum, inputs: {xs: ["plus[*]", "more[*]"]}}')
    assert text != SWEEP
    run_pipeline(pipeline_file(tmp_path, text), [], out_dir=str(tmp_path / "out"), cache_dir=str(tmp_path / "cache"),
                 scheduler="sync")
    more_total = sum(3 * s + 3 * delta for s in (1, 2, 3) for delta in (100, 200))  # (0 + 1 + 2) s + 3 delta
    assert json.loads((tmp_path / "out" / "value.json").read_text()) == SWEEP_TOTAL + more_total


def test_a_map_over_no_value_drops_its_branches_from_the_run(tmp_path, test_nodes):
    """``map: {delta: []}``: the node and the nodes mapped with it have no instance, and a fan-in
    over several mapped nodes sums the others; a fan-in left with nothing receives an empty list."""
    text = SWEEP.replace('tot:   {type: t.sum, inputs: {xs: "plus[*]"}}',
                         'more:  {type: t.add, inputs: {x: src}, map: {delta: "${more_deltas}"}}\n'
                         '  tot:   {type: t.sum, inputs: {xs: ["plus[*]", "more[*]"]}}').replace(
                             "  scales: [1, 2, 3]\n", "  scales: [1, 2, 3]\n  more_deltas: []\n")
    result = run_pipeline(pipeline_file(tmp_path, text), [], out_dir=str(tmp_path / "out"),
                          cache_dir=str(tmp_path / "cache"), scheduler="sync")
    assert json.loads((tmp_path / "out" / "value.json").read_text()) == SWEEP_TOTAL
    assert not [i for i in result.plan.instances if i.node == "more"]
    run_pipeline(pipeline_file(tmp_path, text), ["scales=[]"], out_dir=str(tmp_path / "out2"),
                 cache_dir=str(tmp_path / "cache"), scheduler="sync")
    assert json.loads((tmp_path / "out2" / "value.json").read_text()) == 0
    manifest = json.loads((tmp_path / "out2" / "manifest.json").read_text())
    assert sorted(manifest["files"]) == ["value.json"]  # no branch wrote a mean


PRIORITY = """\
nodes:
  src:  {type: t.source, params: {n: 3}}
  low:  {type: t.add, inputs: {x: src}, map: {delta: [1, 2, 3, 4]}, priority: %d}
  high: {type: t.stats, inputs: {x: src}, priority: %d}
"""


def _started(tmp_path: Path, low: int, high: int, scheduler: str, run: str = "") -> list[str]:
    """Instance ids in the order they started (threads: handed to a worker; one-worker cluster: done)."""
    from retrotouch.graph.execute import execute
    from retrotouch.graph.runner import make_plan

    path = tmp_path / f"p{low}{high}{run}.yaml"
    path.write_text(PRIORITY % (low, high))
    plan = make_plan(str(path), [], str(tmp_path / f"cache{low}{high}{run}"))
    order: list[str] = []
    record = (lambda name: order.append(name.split("-")[0])) if scheduler == "threads" else (lambda name: None)
    done = (lambda name, result: None) if scheduler == "threads" else (lambda name, result: order.append(name.split("-")[0]))
    execute(plan, scheduler, "run", done, record)
    return order


def _start_order(tmp_path: Path, low: int, high: int, scheduler: str) -> list[str]:
    """The node names of :func:`_started`."""
    return [name.split("[")[0] for name in _started(tmp_path, low, high, scheduler)]


def test_priority_starts_first_among_ready_tasks(tmp_path, test_nodes):
    # after src, the four `low` branches and `high` are ready at once: the priority decides, both ways
    assert _start_order(tmp_path, 0, 1, "threads") == ["src", "high", "low", "low", "low", "low"]
    assert _start_order(tmp_path, 1, 0, "threads") == ["src", "low", "low", "low", "low", "high"]


def test_priority_reaches_a_dask_distributed_scheduler(tmp_path, test_nodes):
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp",
                      dashboard_address=None) as cluster:
        address = cluster.scheduler_address
        assert _start_order(tmp_path, 0, 1, address) == ["src", "high", "low", "low", "low", "low"]
        assert _start_order(tmp_path, 1, 0, address) == ["src", "low", "low", "low", "low", "high"]


def test_priority_must_be_a_whole_number(tmp_path, test_nodes):
    (tmp_path / "p.yaml").write_text(PRIORITY.replace("priority: %d}", "priority: high}", 1) % 0)
    with pytest.raises(UserError, match=r"p.yaml:3:\d+: node 'low': priority must be a whole number"):
        run_pipeline(str(tmp_path / "p.yaml"), [], out_dir=str(tmp_path / "out"), cache_dir=str(tmp_path / "cache"))


def test_start_order_puts_the_longest_estimated_chain_first(tmp_path, monkeypatch):
    from types import SimpleNamespace

    from retrotouch.graph import ordering

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    ordering.record_timings({"a": 1.0, "b": 1.0, "c": 5.0, "d": 2.0})
    tasks = {name: (SimpleNamespace(instance_id=name), ups) for name, ups in
             (("a", []), ("d", []), ("b", ["a"]), ("c", ["b"]), ("e", []))}  # e never timed: the median, 1.5 s
    order = ordering.start_order(tasks, dict.fromkeys(tasks, 0))
    assert sorted(tasks, key=order.__getitem__, reverse=True) == ["a", "b", "c", "d", "e"]  # ranks 7, 6, 5, 2, 1.5
    assert max(ordering.start_order(tasks, {**dict.fromkeys(tasks, 0), "e": 1}).items(), key=lambda kv: kv[1])[0] == "e"
    ordering.record_timings({"a": 3.14159})
    assert list(ordering.read_record(ordering.TIMINGS_NAME).items())[-1] == ("a", 3.142)  # the newest last


def test_a_run_starts_first_the_branch_that_took_longest_before(tmp_path, test_nodes, monkeypatch):
    from retrotouch.graph import ordering

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "user"))
    assert _start_order(tmp_path, 0, 0, "threads")[:1] == ["src"]
    assert set(ordering.read_record(ordering.TIMINGS_NAME)) >= {"src", "high", "low[delta=1]", "low[delta=4]"}
    for slow in ("low[delta=3]", "high"):
        ordering.record_timings({slow: 60.0})
        assert _started(tmp_path, 0, 0, "threads", run=f"-{slow[:4]}")[:2] == ["src", slow]
