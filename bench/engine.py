"""Engine benchmark: parallel speed-up of a map: sweep, and the warm rerun of the default pipeline.

1. An 11-branch ``map:`` of pure-Python work (``bench.python_work``, calibrated to about 1 s per
   branch on this machine) run by the CLI with the default scheduler, ``--scheduler sync`` and
   ``--scheduler local-cluster`` (dask.distributed), each with a fresh cache. Speed-up = sync time / default time, from the run time the CLI reports
   (planning, cluster start-up, execution and outputs; the interpreter start-up, identical for both,
   is left out) and from the whole subprocess wall time.
2. ``retrotouch run pipelines/retrofit.yaml`` twice with a fresh cache: the second run (everything
   cached) timed as subprocess wall time, interpreter start-up included.

Prints a table; the LAST line is one JSON object (``map_speedup_vs_sync``, ``warm_rerun_s``, ...).
Usage: ``python bench/engine.py [--branches 11] [--seconds-per-branch 1.0] [--repeat 2]``.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
sys.path.insert(0, str(BENCH))

import engine_nodes  # noqa: E402  (bench node types, also imported by the runs through the env)


def calibrate(seconds: float) -> int:
    """Loop iterations that take about ``seconds`` here (median of three 0.1 s-scale probes: a
    30 ms probe's fastest run overestimated the speed and gave 0.33 s branches)."""
    probe = 1_000_000
    times = []
    for _ in range(3):
        start = time.perf_counter()
        engine_nodes.python_work(engine_nodes.WorkParams(iterations=probe))
        times.append(time.perf_counter() - start)
    return int(probe * seconds / sorted(times)[1])


def cli() -> list[str]:
    script = Path(sys.executable).with_name("retrotouch")
    return [str(script)] if script.exists() else [sys.executable, "-m", "retrotouch.nodes"]


def run(args: list[str], cwd: Path, env: dict[str, str]) -> tuple[float, float, str]:
    """(wall seconds, seconds the CLI reports for the run, stdout)."""
    start = time.perf_counter()
    proc = subprocess.run(cli() + args, cwd=cwd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        sys.exit(f"bench: retrotouch {' '.join(args)} failed: {proc.stderr.strip()}")
    m = re.search(r"(\d+) ran, (\d+) cached, ([\d.]+) s;", proc.stdout)
    return wall, float(m.group(3)), proc.stdout


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--branches", type=int, default=11)
    parser.add_argument("--seconds-per-branch", type=float, default=1.0, help="pure-Python work per branch (the per-angle layout branches of the default pipeline take 1.5-3.5 s)")
    parser.add_argument("--repeat", type=int, default=2, help="map runs per scheduler (best is kept)")
    args = parser.parse_args()

    iterations = calibrate(args.seconds_per_branch)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(BENCH), os.environ.get("PYTHONPATH")])),
           "RETROTOUCH_NODE_MODULES": "engine_nodes"}
    rows = []
    with tempfile.TemporaryDirectory(prefix="retrotouch-bench-") as tmp_name:
        tmp = Path(tmp_name)
        seeds = ", ".join(str(s) for s in range(args.branches))
        (tmp / "map.yaml").write_text(
            f"params:\n  seeds: [{seeds}]\n"
            "nodes:\n"
            f"  work: {{type: bench.python_work, map: {{seed: \"${{seeds}}\"}}, params: {{iterations: {iterations}}}}}\n"
            "  all:  {type: bench.collect, inputs: {parts: \"work[*]\"}}\n")
        timings: dict[str, tuple[float, float]] = {}
        schedulers = ("sync", "auto", "local-cluster")
        for _ in range(args.repeat):  # interleaved; the best of each (the machine may be shared)
            for scheduler in schedulers:
                cache = tmp / f"cache-{scheduler}"
                wall, reported, _ = run(["run", "map.yaml", "--scheduler", scheduler, "--cache-dir", str(cache),
                                         "--out", str(tmp / f"out-{scheduler}")], tmp, env)
                best = timings.get(scheduler, (float("inf"), float("inf")))
                timings[scheduler] = (min(best[0], wall), min(best[1], reported))
                shutil.rmtree(cache)
        for scheduler in schedulers:
            rows.append((f"map x{args.branches}, --scheduler {scheduler} (best of {args.repeat})",
                         timings[scheduler][1], timings[scheduler][0]))
        fixed = {}  # the same map with almost no work: what starting the parallel machinery costs
        for scheduler in schedulers:
            cache = tmp / f"cache-trivial-{scheduler}"
            wall, reported, _ = run(["run", "map.yaml", "-S", "work.iterations=1", "--scheduler", scheduler,
                                     "--cache-dir", str(cache), "--out", str(tmp / f"out-trivial-{scheduler}")], tmp, env)
            fixed[scheduler] = reported
            rows.append((f"map x{args.branches}, no work, --scheduler {scheduler}", reported, wall))
        outputs = [json.loads((tmp / f"out-{s}" / "manifest.json").read_text())["nodes"] for s in schedulers]
        assert all([n["content_sha256"] for n in o] == [n["content_sha256"] for n in outputs[0]] for o in outputs)

        pipeline = str(REPO / "pipelines" / "retrofit.yaml")
        cache = tmp / "cache-default"
        base = ["run", pipeline, "--cache-dir", str(cache), "--out", str(tmp / "out-default")]
        cold_wall, cold_reported, _ = run(base, tmp, dict(os.environ))
        warm_wall, warm_reported, stdout = run(base, tmp, dict(os.environ))
        if not re.search(r"^0 ran,", stdout, re.M):
            sys.exit("bench: the second run of the default pipeline was not all cache hits")
        rows += [("default pipeline, cold", cold_reported, cold_wall), ("default pipeline, warm rerun", warm_reported, warm_wall)]

    speedup = timings["sync"][1] / timings["auto"][1]
    overhead = fixed["auto"] - fixed["sync"]
    rounds = -(-args.branches // (os.cpu_count() or 1))
    ideal = args.branches / rounds  # whole branches per core: 11 on 2 cores take 6 rounds
    speedup_wall = timings["sync"][0] / timings["auto"][0]
    print(f"{'case':52s} {'run s':>8s} {'wall s':>8s}")
    for name, reported, wall in rows:
        print(f"{name:52s} {reported:8.2f} {wall:8.2f}")
    print(f"map speed-up vs sync: {speedup:.2f}x (run time), {speedup_wall:.2f}x (wall); at most {ideal:.2f}x "
          f"({args.branches} branches in {rounds} rounds); parallel start-up costs {overhead:.2f} s; "
          f"{iterations} iterations per branch, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")
    print(json.dumps({"map_speedup_vs_sync": round(speedup, 3), "map_speedup_vs_sync_wall": round(speedup_wall, 3),
                      "map_branches": args.branches, "map_sync_s": round(timings["sync"][1], 3),
                      "map_default_s": round(timings["auto"][1], 3), "map_parallel_overhead_s": round(overhead, 3),
                      "map_local_cluster_speedup_vs_sync": round(timings["sync"][1] / timings["local-cluster"][1], 3),
                      "map_local_cluster_overhead_s": round(fixed["local-cluster"] - fixed["sync"], 3),
                      "map_ideal_speedup": round(ideal, 3), "warm_rerun_s": round(warm_wall, 3),
                      "cold_run_s": round(cold_wall, 3), "cores": os.cpu_count(),
                      "load_average": round(os.getloadavg()[0], 2)}))


if __name__ == "__main__":
    main()
