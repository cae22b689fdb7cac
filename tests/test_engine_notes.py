"""A node's one-line note (``note=`` of ``graph.node.node``) is stored with its cached value and shown in the run
summary (table and ``--json``) and in ``manifest.json`` whether the node ran or was a cache hit."""
from __future__ import annotations

import json
import os
import textwrap

import pytest

from retrotouch.graph.node import REGISTRY, node

NODE_MODULE = '''
from retrotouch.graph.node import Files, NodeParams, node


class Params(NodeParams):
    n: int = 3


@node("note.count", params=Params, outputs=("out",), note=lambda values: f"counted {len(values)} values")
def count(params: Params) -> list:
    """0..n-1."""
    return list(range(params.n))


@node("note.write", inputs=("value",), outputs=("files",), sink=True)
def write(params, value) -> Files:
    """value.json."""
    import json
    return Files({"value.json": json.dumps(value).encode()})
'''

PIPELINE = textwrap.dedent("""\
    nodes:
      count: {type: note.count, params: {n: 4}}
      out:   {type: note.write, inputs: {value: count}}
    """)


@pytest.fixture
def note_nodes(tmp_path, monkeypatch):
    folder = tmp_path / "mods"
    folder.mkdir()
    (folder / "rt_notenodes.py").write_text(NODE_MODULE)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(folder), os.environ.get("PYTHONPATH")])))
    monkeypatch.setenv("RETROTOUCH_NODE_MODULES", "rt_notenodes")


def test_note_is_shown_when_ran_and_when_cached(tmp_path, cli, note_nodes):
    (tmp_path / "p.yaml").write_text(PIPELINE)
    for expected_status in ("ran", "cached"):
        table = cli("run", "p.yaml", "--out", "out", "--cache-dir", "cache")
        assert table.returncode == 0, table.stderr
        assert "count: counted 4 values\n" in table.stdout
        manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
        by_node = {n["node"]: n for n in manifest["nodes"]}
        assert by_node["count"]["note"] == "counted 4 values" and by_node["out"]["note"] is None
        assert by_node["count"]["status"] == expected_status
        assert json.loads((tmp_path / "out" / "value.json").read_text()) == [0, 1, 2, 3]
    summary = json.loads(cli("run", "p.yaml", "--out", "out", "--cache-dir", "cache", "--json").stdout)
    assert [(n["id"], n["status"], n["note"]) for n in summary["nodes"]] == [
        ("count", "cached", "counted 4 values"), ("out", "cached", None)]


def test_a_note_is_one_line():
    @node("note.two_lines", note=lambda value: "two\nlines")
    def two_lines(params) -> int:
        """A bad note."""
        return 1

    @node("note.silent")
    def silent(params) -> int:
        """No note."""
        return 1

    try:
        with pytest.raises(TypeError, match="one-line"):
            REGISTRY["note.two_lines"].note_of(1)
        assert REGISTRY["note.silent"].note_of(1) is None
    finally:
        del REGISTRY["note.silent"]
        del REGISTRY["note.two_lines"]
