"""``watch``: reruns on every save, one self-updating page with the graph and node states, a typo
shown on the page while the last good result stays; checked in headless Chromium."""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest
from chromium import run_chromium

PIPELINE = """\
nodes:
  src:   {type: t.source, map: {scale: [1, 2, 3]}, params: {n: 3}}
  plus:  {type: t.add, inputs: {x: src}, params: {delta: 10}}
  tot:   {type: t.sum, inputs: {xs: "plus[*]"}}
  out:   {type: t.write, inputs: {value: tot}}
  rows:  {type: t.rows, inputs: {xs: "plus[*]"}}
  table: {type: t.write, inputs: {value: rows}, params: {filename: per_branch.json}}
  pic:   {type: t.picture, inputs: {value: tot}}
"""


def _dom(url: str, profile: Path) -> str:
    return run_chromium(["--virtual-time-budget=3000", "--dump-dom", url], profile, 90)


def _state(url: str) -> dict:
    with urllib.request.urlopen(url + "state.json", timeout=10) as r:
        return json.loads(r.read())


def _wait(url: str, test, what: str, timeout: float = 120) -> dict:
    deadline = time.time() + timeout
    while time.time() < deadline:
        state = _state(url)
        if test(state):
            return state
        time.sleep(0.2)
    pytest.fail(f"the watch never got to {what}: {state}")


def _node_states(dom: str) -> dict[str, str]:
    return dict(re.findall(r'<tr class="state-\w+"><td>(\w+)</td><td>\d+</td><td data-state="(\w+)">', dom))


def test_watch_reruns_on_save_and_keeps_the_last_good_result(tmp_path, test_nodes):
    if shutil.which("chromium") is None:
        pytest.skip("chromium is not installed (apt-get install -y chromium): the watch page is not checked")
    pipeline = tmp_path / "p.yaml"
    pipeline.write_text(PIPELINE)
    proc = subprocess.Popen([sys.executable, "-m", "retrotouch.nodes", "watch", "p.yaml", "--port", "0", "--out", "out"],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        first_line = proc.stdout.readline()
        url = re.search(r"(http://127\.0\.0\.1:\d+/)", first_line).group(1)
        _wait(url, lambda s: s["phase"] == "ok", "a first result")
        dom = _dom(url, tmp_path / "profile")
        assert _node_states(dom) == {n: "ran" for n in ("src", "plus", "tot", "out", "rows", "table", "pic")}
        assert '<img class="out" src="/files/picture.svg"' in dom
        assert "<td>index</td>" not in dom and "<th>index</th><th>total</th>" in dom  # the records as a table
        assert "<td>33</td>" in dom and "<td>39</td>" in dom  # per-branch totals 3 * scale + 30
        if shutil.which("dot"):
            with urllib.request.urlopen(url + "graph.svg", timeout=10) as r:
                assert b"<svg" in r.read()
        # a typo: the error on the page, the last good result still there
        pipeline.write_text(PIPELINE.replace("delta: 10}", "delta: [10}"))
        _wait(url, lambda s: s["phase"] == "error", "the typo's error")
        dom = _dom(url, tmp_path / "profile")
        error = re.search(r'<div id="error">([^<]*)</div>', dom).group(1)
        assert error.startswith("p.yaml:3:") and "YAML syntax error" in error
        assert "<td>36</td>" in dom and json.loads((tmp_path / "out" / "value.json").read_text()) == 3 * 6 + 90
        # fixed, with a slow source: the page shows it running, then the new result
        pipeline.write_text(PIPELINE.replace("delta: 10", "delta: 20").replace("n: 3}", "n: 3, sleep_s: 3}"))
        _wait(url, lambda s: any(n["state"] == "running" for n in s["nodes"]), "a running node")
        assert _node_states(_dom(url, tmp_path / "profile"))["src"] == "running"
        state = _wait(url, lambda s: s["result_version"] == 2, "the second result")
        assert state["phase"] == "ok" and state["error"] == ""
        dom = _dom(url, tmp_path / "profile")
        assert "<td>66</td>" in dom and "<td>36</td>" not in dom and re.search(r'<div id="error" hidden', dom)
        assert json.loads((tmp_path / "out" / "value.json").read_text()) == 3 * 6 + 180
    finally:
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    assert (proc.returncode, err) == (130, "retrotouch: error: interrupted\n")
