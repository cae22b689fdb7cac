"""Two runs of the fabrication sinks give byte-identical files (issue 17 #10): deterministic nesting,
PDF/DXF creation times from SOURCE_DATE_EPOCH (else a fixed time), fixed DXF GUIDs."""
from __future__ import annotations

import datetime
import re

import pytest
import trimesh
from fab_layouts import mesh_from_trimesh, section_layout

from retrotouch.nodes.fab.assembly_guide import Params as GuideParams
from retrotouch.nodes.fab.assembly_guide import assembly_guide
from retrotouch.nodes.fab.cut_sheets import Params as SheetParams
from retrotouch.nodes.fab.cut_sheets import cut_sheets
from retrotouch.nodes.fab.nesting import Params as NestParams
from retrotouch.nodes.fab.nesting import nest
from retrotouch.nodes.fab.outline import Params as OutlineParams
from retrotouch.nodes.fab.outline import outline
from retrotouch.nodes.fab.unfold import Params as UnfoldParams
from retrotouch.nodes.fab.unfold import unfold

SPHERE = mesh_from_trimesh(trimesh.creation.icosphere(subdivisions=3, radius=45.0), "icosphere r45")


def run_sinks() -> dict[str, bytes]:
    """Nest and write everything from scratch (a fresh nesting each time)."""
    layout = section_layout(SPHERE, 4, 3)
    outlines = outline(OutlineParams(), unfold(UnfoldParams(), SPHERE, layout))
    nested = nest(NestParams(mat="custom", sheet_width_mm=260, sheet_height_mm=120), outlines)
    files = dict(cut_sheets(SheetParams(), outlines, nested).contents)
    files.update(cut_sheets(SheetParams(dxf_version="R12"), outlines, nested).contents)  # R12 replaces the DXFs
    files.update(assembly_guide(GuideParams(image_px=100, views_per_trace=1), SPHERE, layout, outlines).contents)
    return files


@pytest.mark.parametrize("epoch", [None, "1700000000"])
def test_two_runs_give_identical_files(monkeypatch, epoch):
    if epoch is None:
        monkeypatch.delenv("SOURCE_DATE_EPOCH", raising=False)
    else:
        monkeypatch.setenv("SOURCE_DATE_EPOCH", epoch)
    first = run_sinks()
    second = run_sinks()
    assert first.keys() == second.keys() and "sheets/sheet_1.pdf" in first and "assembly_guide.pdf" in first
    different = [name for name in first if first[name] != second[name]]
    assert different == []
    when = datetime.datetime(2000, 1, 1) if epoch is None else datetime.datetime.utcfromtimestamp(int(epoch))
    stamp = when.strftime("%Y%m%d%H%M%S").encode()
    assert re.search(rb"/CreationDate \(D:" + stamp, first["sheets/sheet_1.pdf"])
    assert re.search(rb"/CreationDate \(D:" + stamp, first["assembly_guide.pdf"])
    from ezdxf.tools import juliandate

    assert f"$TDCREATE\n 40\n{juliandate(when)}\n" in first["sheets/sheet_1.dxf"].decode()


def test_dxf_is_the_same_in_every_process():
    """ezdxf writes the CLASS entries of the entity types in use in set order, which follows the
    per-process string hash seed: the writer sorts them first."""
    import os
    import subprocess
    import sys

    script = (
        "import hashlib, numpy as np\n"
        "from retrotouch.nodes.fab.cut_sheets import sheet_dxf\n"
        "square = np.array([[0, 0], [10, 0], [10, 10], [0, 10.0]])\n"
        "print(hashlib.sha256(sheet_dxf([square, square + 20], [square / 5], 100.0, 50.0, 3)).hexdigest())\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    digests = {subprocess.run([sys.executable, "-c", script], env={**env, "PYTHONHASHSEED": str(seed)}, check=True,
                              capture_output=True, text=True).stdout for seed in range(8)}
    assert len(digests) == 1
