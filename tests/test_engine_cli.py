"""The CLI around the engine: nodes, plan, cache maintenance, extension commands, one-line errors."""
from __future__ import annotations

import json
import os
import re
import time
from pathlib import Path

import pytest
import typer

from retrotouch.graph import cli
from retrotouch.graph.app import App, configure
from retrotouch.nodes.app import APP, main as app_main
from retrotouch.graph.runner import run_pipeline
from retrotouch.graph.store import Store

PIPELINE = """\
nodes:
  src:  {type: t.source, map: {scale: [1, 2]}}
  tot:  {type: t.sum, inputs: {xs: "src[*]"}}
  out:  {type: t.write, inputs: {value: tot}}
"""


def main(capsys, *args: str) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as info:
        app_main(list(args))
    captured = capsys.readouterr()
    return info.value.code, captured.out, captured.err


def test_nodes_lists_types_params_and_docs(capsys, test_nodes):
    code, out, _ = main(capsys, "nodes", "t.source")
    assert code == 0
    assert "t.source" in out and "0, 1, ..., n-1 times scale." in out
    assert "n: int (default 4) - number of values" in out
    assert "t.add" not in out


def test_plan_shows_hits_and_misses(tmp_path, capsys, test_nodes, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "p.yaml").write_text(PIPELINE)
    code, out, _ = main(capsys, "plan", "p.yaml")
    assert code == 0 and "4 of 4 node instances would run" in out and "no previous run recorded" in out
    run_pipeline("p.yaml", scheduler="sync")
    code, out, _ = main(capsys, "plan", "p.yaml", "-S", "nodes.src.map.scale=[1, 3]")
    assert code == 0 and "3 of 4 node instances would run" in out


def test_cache_info_gc_clear(tmp_path, capsys, test_nodes, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "p.yaml").write_text(PIPELINE)
    run_pipeline("p.yaml", scheduler="sync")
    run_pipeline("p.yaml", ["nodes.src.map.scale=[5]"], scheduler="sync")
    store = Store(str(tmp_path / "cache"))
    assert len(store.entries()) == 4 + 3
    stale = tmp_path / "cache" / "tmp" / "left-by-a-killed-run"
    stale.mkdir(parents=True)
    os.utime(stale, (time.time() - 7200, time.time() - 7200))
    code, out, _ = main(capsys, "cache", "info")
    assert code == 0 and "entries:   7" in out and "temp dirs: 1" in out
    code, out, _ = main(capsys, "cache", "gc", "p.yaml")
    assert code == 0 and "removed 1 stale temp dirs, 0 corrupt entries, 3 unused entries" in out
    assert len(store.entries()) == 4 and not stale.exists()
    code, out, _ = main(capsys, "cache", "gc", "--older-than", "1")
    assert code == 0 and "0 unused entries" in out  # everything was used just now
    code, out, _ = main(capsys, "cache", "clear")
    assert code == 0 and store.entries() == []


def test_cache_gc_refuses_a_negative_or_infinite_age_and_removes_nothing(tmp_path, capsys, test_nodes, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "p.yaml").write_text(PIPELINE)
    run_pipeline("p.yaml", scheduler="sync")
    store = Store(str(tmp_path / "cache"))
    assert len(store.entries()) == 4
    for days in ("-3", "nan", "inf"):
        code, out, err = main(capsys, "cache", "gc", "--older-than", days)
        assert code == 2 and out == "" and err == f"retrotouch: error: --older-than {days}: DAYS must be a finite " \
                                                  "number of days >= 0, e.g. --older-than 30\n"
    assert len(store.entries()) == 4


def test_errors_are_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, _, err = main(capsys, "run")
    assert code == 2 and err.count("\n") == 1 and err.startswith("retrotouch: error: Missing argument")
    code, _, err = main(capsys, "frobnicate")
    assert code == 2 and err.count("\n") == 1 and "No such command" in err
    code, _, err = main(capsys, "run", "p.yaml", "--scheduler", "gpu")
    assert code == 2 and err == "retrotouch: error: --scheduler 'gpu': expected one of auto, sync, threads, " \
                                "processes, local-cluster or tcp://HOST:PORT\n"


def test_extension_modules_add_commands_and_missing_ones_are_skipped(tmp_path, monkeypatch):
    (tmp_path / "rt_ext_hello.py").write_text(
        "def register(app):\n    @app.command('hello')\n    def hello():\n        'Say hello.'\n        print('hi')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    configure(App(APP.name, APP.node_packages, cli_extensions=("rt_ext_not_written_yet", "rt_ext_hello")))
    try:
        command = typer.main.get_command(cli.build_app())
    finally:
        configure(APP)
    assert {"run", "plan", "nodes", "cache", "hello"} <= set(command.commands)


def test_discovery_finds_package_nodes_and_names_a_broken_module(tmp_path, monkeypatch):
    from retrotouch.graph import registry
    from retrotouch.graph.errors import UserError

    specs = registry.load()
    assert {"mesh.load", "mesh.scale", "mesh.export"} <= set(specs)
    assert specs["mesh.export"].sink
    (tmp_path / "rt_broken_nodes.py").write_text("raise RuntimeError('boom')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("RETROTOUCH_NODE_MODULES", "rt_broken_nodes")
    with pytest.raises(UserError, match="cannot import node module rt_broken_nodes: RuntimeError: boom"):
        registry.load()
    monkeypatch.setenv("RETROTOUCH_NODE_MODULES", "rt_no_such_module")
    with pytest.raises(UserError, match="RETROTOUCH_NODE_MODULES names module 'rt_no_such_module'"):
        registry.load()


# -- pipeline-tool habits (issue 15 item 4) --------------------------------------------------------
SCHEMAS = Path(__file__).resolve().parents[1] / "graph" / "schemas"
LONG = "a_node_name_long_enough_to_be_cut_by_an_eighty_column_terminal_if_anything_cut_it"
LONG_PIPELINE = f"""\
nodes:
  src:   {{type: t.source, map: {{scale: [1, 2]}}, params: {{n: 3}}}}
  {LONG}: {{type: t.add, inputs: {{x: src}}, params: {{delta: 10}}}}
  tot:   {{type: t.sum, inputs: {{xs: "{LONG}[*]"}}}}
  out:   {{type: t.write, inputs: {{value: tot}}}}
  side:  {{type: t.write, inputs: {{value: src}}, params: {{filename: side.json}}}}
"""


def test_version_and_short_help(capsys):
    import tomllib

    version = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"]["version"]
    for flag in ("--version", "-V"):
        code, out, _ = main(capsys, flag)
        assert code == 0 and out.startswith(f"retrotouch {version}") and out.count("\n") == 1
    code, out, _ = main(capsys, "-h")
    assert code == 0 and out.startswith("Usage: retrotouch") and "dag" in out and "--version" in out
    assert "..." not in out.split("Commands:")[1]  # every command's first sentence whole
    code, out, _ = main(capsys, "run", "-h")
    assert code == 0 and "--target" in out and "--json" in out


def test_piped_tables_are_never_cut_and_a_cached_run_is_one_line(tmp_path, cli, test_nodes):
    (tmp_path / "p.yaml").write_text(LONG_PIPELINE)
    first = cli("run", "p.yaml", "--out", "out")
    assert first.returncode == 0, first.stderr
    rows = [line.split() for line in first.stdout.splitlines()]
    assert rows[0] == ["node", "branch", "cached/ran", "seconds"]
    assert [LONG, "scale=1", "ran"] == rows[3][:3] and "…" not in first.stdout
    assert max(map(len, first.stdout.splitlines())) > 80
    plan = cli("plan", "p.yaml")
    assert plan.returncode == 0 and f"{LONG}  scale=2" in plan.stdout and "…" not in plan.stdout
    again = cli("run", "p.yaml", "--out", "out")
    assert again.returncode == 0 and again.stdout.count("\n") == 1
    assert re.fullmatch(r"0 ran, 8 cached, \d+\.\d\d s; outputs in .*\n", again.stdout)


def test_json_run_summary_and_manifest_follow_their_schemas(tmp_path, cli, test_nodes):
    import jsonschema

    (tmp_path / "p.yaml").write_text(LONG_PIPELINE)
    result = cli("run", "p.yaml", "--out", "out", "--json", "-S", "src.n=2")
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    jsonschema.validate(summary, json.loads((SCHEMAS / "run-summary.schema.json").read_text()))
    assert (summary["ran"], summary["cached"]) == (8, 0) and summary["nodes"][0]["id"] == "src[scale=1]"
    schema = json.loads((SCHEMAS / "manifest.schema.json").read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    jsonschema.validate(manifest, schema)
    assert manifest["format"] == "retrotouch.manifest/2"
    broken = [{**manifest, "format": "retrotouch.manifest/1"}, {k: v for k, v in manifest.items() if k != "files"},
              {**manifest, "files": {"value.json": {**manifest["files"]["value.json"], "sha256": "abc"}}},
              {**manifest, "files": {"../escape": manifest["files"]["value.json"]}}]
    for bad in broken:
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(bad, schema)


def test_target_runs_a_node_and_what_it_needs(tmp_path, cli, test_nodes):
    (tmp_path / "p.yaml").write_text(LONG_PIPELINE)
    result = cli("run", "p.yaml", "--out", "out", "--target", "side", "--json")
    assert result.returncode == 0, result.stderr
    assert [n["id"] for n in json.loads(result.stdout)["nodes"]] == ["src[scale=1]", "src[scale=2]", "side[scale=1]",
                                                                     "side[scale=2]"]
    assert sorted(json.loads((tmp_path / "out" / "manifest.json").read_text())["files"]) == \
        ["scale=1/side.json", "scale=2/side.json"]
    full = cli("run", "p.yaml", "--out", "out", "--json")
    assert json.loads(full.stdout)["ran"] == 4  # the two src branches were computed by the targeted run
    bad = cli("run", "p.yaml", "--target", "sid")
    assert bad.returncode == 2 and "--target 'sid': no such node; did you mean 'side'?" in bad.stderr


def test_dag_as_mermaid_dot_and_svg(tmp_path, cli, test_nodes):
    import shutil
    import xml.etree.ElementTree as ET

    (tmp_path / "p.yaml").write_text(LONG_PIPELINE)
    mermaid = cli("dag", "p.yaml")
    assert mermaid.returncode == 0 and mermaid.stdout.startswith("flowchart TD\n")
    assert 'n0["src<br/>t.source<br/>× 2 (scale)"]' in mermaid.stdout and "n2 -->|value| n3" in mermaid.stdout
    assert mermaid.stdout.count("-->") == 4 and "|xs[*]|" in mermaid.stdout
    dot = cli("dag", "p.yaml", "--format", "dot", "--status")
    assert dot.returncode == 0 and dot.stdout.count(" -> ") == 4 and "would run" in dot.stdout
    assert cli("dag", "p.yaml", "--format", "png").returncode == 2
    if shutil.which("dot") is None:
        pytest.skip("Graphviz's dot is not installed: SVG output not checked")
    svg = cli("dag", "p.yaml", "--format", "svg")
    assert svg.returncode == 0, svg.stderr
    root = ET.fromstring(svg.stdout.split("-->", 1)[1] if svg.stdout.startswith("<?xml") else svg.stdout)
    texts = [t.text for t in root.iter("{http://www.w3.org/2000/svg}text")]
    assert LONG in texts and "tot" in texts


def test_progress_names_the_running_nodes_with_their_elapsed_time(tmp_path, test_nodes):
    import pty
    import select
    import subprocess
    import sys

    (tmp_path / "p.yaml").write_text("nodes:\n  slow: {type: t.source, map: {scale: [1, 2]}, params: {sleep_s: 2.2}}\n")
    master, slave = pty.openpty()
    proc = subprocess.Popen([sys.executable, "-m", "retrotouch.nodes", "run", "p.yaml", "--scheduler", "sync"],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=slave, env={**os.environ, "COLUMNS": "120"})
    os.close(slave)
    seen = b""
    try:
        while True:
            ready, _, _ = select.select([master], [], [], 30)
            if not ready:
                break
            try:
                chunk = os.read(master, 65536)
            except OSError:
                break
            if not chunk:
                break
            seen += chunk
    finally:
        proc.communicate(timeout=60)
        os.close(master)
    text = seen.decode("utf-8", "replace")
    assert proc.returncode == 0
    assert "running: slow[scale=1] 1s" in text and "running: slow[scale=1] 2s" in text  # the clock moves
    assert "running: slow[scale=2] 1s" in text and "1/2" in text
