"""The mesh.export sink: a binary PLY that reads back exactly."""
from __future__ import annotations

import io

import numpy as np
import pytest
import trimesh
from pydantic import ValidationError

from retrotouch.graph.node import Files
from retrotouch.nodes.data.types import Mesh
from retrotouch.nodes.data.ply import ply_bytes
from retrotouch.nodes.mesh.export import ExportParams, export_mesh


def tetrahedron() -> Mesh:
    v = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]], dtype=np.float64)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.int64)
    return Mesh(v, f, "test")


def test_ply_reads_back_exactly():
    mesh = tetrahedron()
    files = export_mesh(ExportParams(), mesh)
    assert isinstance(files, Files) and list(files.contents) == ["mesh.ply"]
    back = trimesh.load(io.BytesIO(files.contents["mesh.ply"]), file_type="ply", process=False)
    assert np.array_equal(back.vertices, mesh.vertices)
    assert np.array_equal(back.faces, mesh.faces)
    assert back.volume == pytest.approx(1000 / 6)  # CCW outward winding kept: positive volume


def test_ply_size_is_header_plus_fixed_records():
    mesh = tetrahedron()
    data = ply_bytes(mesh.vertices, mesh.faces)
    header_end = data.index(b"end_header\n") + len(b"end_header\n")
    assert len(data) - header_end == 4 * 3 * 8 + 4 * (1 + 3 * 4)


def test_bad_file_name_and_faces_are_refused():
    with pytest.raises(ValidationError, match="ending with .ply"):
        ExportParams(filename="../mesh.stl")
    with pytest.raises(ValueError, match="out of range"):
        ply_bytes(np.zeros((3, 3)), np.array([[0, 1, 3]]))
