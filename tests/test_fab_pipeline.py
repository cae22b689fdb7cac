"""The fabrication nodes inside the engine: artifacts stored, sheets and guide in the output folder
and listed in manifest.json."""
from __future__ import annotations

import json
from pathlib import Path

from retrotouch.graph.runner import run_pipeline

PIPELINE = """
nodes:
  layout:
    type: fabtest.sphere_layout
  unfolded:
    type: fab.unfold
    inputs: {mesh: layout.mesh, layout: layout.layout}
  outlines:
    type: fab.outline
    inputs: {unfolded: unfolded}
  nested:
    type: fab.nest
    inputs: {outlines: outlines}
    params: {nester: shelf}
  sheets:
    type: fab.cut_sheets
    inputs: {outlines: outlines, nesting: nested}
  guide:
    type: fab.assembly_guide
    inputs: {mesh: layout.mesh, layout: layout.layout, outlines: outlines}
    params: {image_px: 100, views_per_trace: 1}
"""


def test_fabrication_nodes_run_in_the_engine(tmp_path: Path, monkeypatch):
    monkeypatch.setenv("RETROTOUCH_NODE_MODULES", "fab_test_nodes")
    (tmp_path / "fab.yaml").write_text(PIPELINE)
    out = tmp_path / "out"
    result = run_pipeline(str(tmp_path / "fab.yaml"), out_dir=str(out), scheduler="sync",
                          cache_dir=str(tmp_path / "cache"))
    assert set(result.ran()) == {"layout", "unfolded", "outlines", "nested", "sheets", "guide"}
    manifest = json.loads((out / "manifest.json").read_text())
    listed = json.dumps(manifest)
    for name in ("sheets/sheet_1.svg", "sheets/sheet_1.pdf", "sheets/sheet_1.dxf", "sheets/preview.png",
                 "sheets/report.json", "assembly_guide.pdf"):
        assert (out / name).is_file() and name in listed
    again = run_pipeline(str(tmp_path / "fab.yaml"), out_dir=str(tmp_path / "out2"), scheduler="sync",
                         cache_dir=str(tmp_path / "cache"))
    assert again.ran() == []  # every artifact came back from the cache
    assert (tmp_path / "out2" / "sheets" / "sheet_1.svg").read_bytes() == (out / "sheets" / "sheet_1.svg").read_bytes()
