"""The CLI around the engine: nodes, plan, cache maintenance, extension commands, one-line errors."""
from __future__ import annotations

import os
import time

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
