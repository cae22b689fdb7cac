"""Scale benchmark: the default pipeline on the bunny at 20k / 50k / 100k vertices, cold cache.

Each size runs ``retrotouch run pipelines/retrofit.yaml -S vertices=N`` in a fresh process with an
empty cache (``--sizes`` to choose others, ``--keep-cache DIR`` to keep the caches for later
reruns). Per-stage seconds are the node seconds recorded in the run's ``manifest.json``, summed
over a node's branches (so the mapped layout stages count CPU-seconds of all branches, while the
wall clock of the run overlaps them on the cores). Peak memory is sampled every 0.2 s over the
whole process tree (the run and any workers it starts): ``peak_rss_mb`` is the summed PSS (shared
pages counted once), ``peak_rss_sum_mb`` the summed RSS (shared pages counted per process). The exponent is the least-squares slope of
log(seconds) over log(vertices), for the whole run and per stage. CPU seconds (user + system of
the run and every process it waited for) are reported beside the wall clock: on a shared,
loaded machine they are the figure that compares across runs.

Prints a table, then as its LAST line one JSON object with ``seconds_by_vertices``,
``peak_rss_mb_by_vertices``, ``exponent``, ``stage_seconds_by_vertices`` and ``stage_exponent``.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil

REPO = Path(__file__).resolve().parents[1]
PIPELINE = REPO / "pipelines" / "retrofit.yaml"


def tree_memory_bytes(process: psutil.Process) -> tuple[int, int]:
    """(summed PSS, summed RSS) of a process and all its descendants (0 for the ones that just exited).

    PSS shares each page among the processes mapping it, so forked workers' shared pages count
    once; RSS counts them in every process (an upper bound).
    """
    pss = rss = 0
    try:
        tree = [process, *process.children(recursive=True)]
    except psutil.Error:  # exited between two samples
        return 0, 0
    for p in tree:
        try:
            info = p.memory_full_info()
            pss += getattr(info, "pss", info.rss)
            rss += info.rss
        except psutil.Error:
            pass
    return pss, rss


def run_once(vertices: int, cache_dir: Path, out_dir: Path) -> dict:
    """One cold run: wall and CPU seconds, peak tree memory (MB) and per-node seconds from the manifest."""
    command = [sys.executable, "-m", "retrotouch.nodes", "run", str(PIPELINE), "-S", f"vertices={vertices}",
               "--out", str(out_dir), "--cache-dir", str(cache_dir)]
    start = time.perf_counter()
    log = out_dir.parent / "stderr.txt"
    with open(log, "w") as err:
        child = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=err)
    watched = psutil.Process(child.pid)
    peak_pss = peak_rss = 0
    while True:
        done, status, usage = os.wait4(child.pid, os.WNOHANG)
        if done:
            break
        pss, rss = tree_memory_bytes(watched)
        peak_pss, peak_rss = max(peak_pss, pss), max(peak_rss, rss)
        time.sleep(0.2)
    seconds = time.perf_counter() - start
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"run at {vertices} vertices failed ({status}): {log.read_text()[-2000:]}")
    manifest = json.loads((out_dir / "manifest.json").read_text())
    stages: dict[str, float] = {}
    for entry in manifest["nodes"]:
        stages[entry["node"]] = stages.get(entry["node"], 0.0) + float(entry.get("seconds") or 0.0)
    return {"seconds": seconds, "cpu_seconds": usage.ru_utime + usage.ru_stime, "peak_rss_mb": peak_pss / 2**20,
            "peak_rss_sum_mb": peak_rss / 2**20, "stages": stages}


def slope(sizes: list[int], seconds: list[float]) -> float:
    """Least-squares exponent b of seconds ~ a * vertices^b (NaN with fewer than two positive points)."""
    pairs = [(n, s) for n, s in zip(sizes, seconds) if s > 0]
    if len(pairs) < 2:
        return float("nan")
    x, y = np.log([p[0] for p in pairs]), np.log([p[1] for p in pairs])
    return float(np.polyfit(x, y, 1)[0])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="20000,50000,100000", help="comma-separated vertex counts")
    parser.add_argument("--keep-cache", type=Path, default=None, help="keep each size's cache in DIR/<N>")
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    results = {}
    with tempfile.TemporaryDirectory(prefix="retrotouch-scale-") as scratch:
        for n in sizes:
            root = args.keep_cache / str(n) if args.keep_cache else Path(scratch) / str(n)
            root.mkdir(parents=True, exist_ok=True)
            results[n] = run_once(n, root / "cache", root / "out")
            print(f"{n} vertices: {results[n]['seconds']:.1f} s ({results[n]['cpu_seconds']:.1f} CPU-s), peak {results[n]['peak_rss_mb']:.0f} MB "
                  f"(summed RSS {results[n]['peak_rss_sum_mb']:.0f} MB)", flush=True)
    stage_names = list(results[sizes[0]]["stages"])
    stage_exponent = {s: slope(sizes, [results[n]["stages"].get(s, 0.0) for n in sizes]) for s in stage_names}
    print(f"{'stage':<14}" + "".join(f"{n:>10}" for n in sizes) + f"{'exponent':>10}")
    for s in sorted(stage_names, key=lambda s: -results[sizes[-1]]["stages"].get(s, 0.0)):
        print(f"{s:<14}" + "".join(f"{results[n]['stages'].get(s, 0.0):>10.1f}" for n in sizes) + f"{stage_exponent[s]:>10.2f}")
    exponent = slope(sizes, [results[n]["seconds"] for n in sizes])
    print(f"{'wall':<14}" + "".join(f"{results[n]['seconds']:>10.1f}" for n in sizes) + f"{exponent:>10.2f}")
    cpu_exponent = slope(sizes, [results[n]["cpu_seconds"] for n in sizes])
    print(f"{'CPU-s':<14}" + "".join(f"{results[n]['cpu_seconds']:>10.1f}" for n in sizes) + f"{cpu_exponent:>10.2f}")
    print(f"{'peak PSS MB':<14}" + "".join(f"{results[n]['peak_rss_mb']:>10.0f}" for n in sizes))
    print(f"{'peak RSS sum':<14}" + "".join(f"{results[n]['peak_rss_sum_mb']:>10.0f}" for n in sizes))
    print(json.dumps({
        "seconds_by_vertices": {str(n): round(results[n]["seconds"], 2) for n in sizes},
        "peak_rss_mb_by_vertices": {str(n): round(results[n]["peak_rss_mb"], 1) for n in sizes},
        "peak_rss_sum_mb_by_vertices": {str(n): round(results[n]["peak_rss_sum_mb"], 1) for n in sizes},
        "exponent": round(exponent, 3),
        "cpu_seconds_by_vertices": {str(n): round(results[n]["cpu_seconds"], 1) for n in sizes},
        "cpu_exponent": round(cpu_exponent, 3),
        "stage_seconds_by_vertices": {str(n): {s: round(v, 2) for s, v in results[n]["stages"].items()} for n in sizes},
        "stage_exponent": {s: round(v, 3) for s, v in stage_exponent.items()},
    }))


if __name__ == "__main__":
    main()
