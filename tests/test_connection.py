"""curves.connection: trivial connections realize exactly the prescribed singularities."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from curves_fixture import SHARED_MESHES, bunny, prepared, sample_mesh_path
from touch_fixture import touch_of
from retrotouch.graph.errors import UserError
from retrotouch.nodes.curves.connection import ConnectionParams, compute_field, connection, genus_check
from retrotouch.nodes.data.types import Mesh
from retrotouch.nodes.geometry.mesh_tables import angle_defects, build_tables, edge_transport, wrap_angle
from retrotouch.nodes.regions.detect import RegionParams, detect_regions


def icosphere_mesh() -> Mesh:
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=170.0 / (2 * np.sqrt(3)))
    return Mesh(vertices=np.asarray(sphere.vertices, dtype=np.float64), faces=np.asarray(sphere.faces, dtype=np.int64), source="icosphere")


def assert_prescribed(mesh: Mesh, regions) -> None:
    tables = build_tables(mesh.vertices, mesh.faces)
    for layer, expected in (("tx", {int(regions.base_centre), int(regions.far_vertex)}), ("rx", set(np.asarray(regions.base_dipole).tolist()))):
        field = compute_field(tables, layer, regions)
        nonzero = np.flatnonzero(field.realized_index)
        assert set(nonzero.tolist()) == expected
        assert np.all(field.realized_index[nonzero] == 1)
        assert field.indices_ok


def test_bunny_indices_and_node_contract():
    mesh, regions, tables, tx, rx = bunny()
    field = connection(ConnectionParams(layer="rx"), mesh, regions)
    assert field.indices_ok and field.layer == "rx"
    np.testing.assert_array_equal(np.flatnonzero(field.realized_index), np.sort(regions.base_dipole))
    np.testing.assert_array_equal(np.flatnonzero(tx.realized_index), np.sort([regions.base_centre, regions.far_vertex]))
    # unit directions in the face planes
    assert np.allclose(np.linalg.norm(tx.face_direction, axis=1), 1.0)
    assert np.abs(np.einsum("fj,fj->f", tx.face_direction, tables.normals)).max() < 1e-12


def test_holonomy_matches_indices():
    """d0^T x = -K + 2 pi k: the solved angles close up around every vertex star."""
    mesh, regions, tables, tx, _ = bunny()
    k = np.zeros(len(mesh.vertices))
    k[[regions.base_centre, regions.far_vertex]] = 1
    residual = tables.d0().T @ tx.connection_angle + angle_defects(tables) - 2 * np.pi * k
    assert np.abs(residual).max() < 1e-8
    # the field is the transport of face 0 by rho + x along every dual edge (mod 2 pi)
    ef = tables.edge_faces
    jump = wrap_angle(tx.face_angle[ef[:, 1]] - tx.face_angle[ef[:, 0]] - edge_transport(tables) - tx.connection_angle)
    assert np.abs(jump).max() < 1e-8


def test_tx_field_points_away_from_far_vertex():
    mesh, regions, tables, tx, _ = bunny()
    ring = np.flatnonzero(np.any(mesh.faces == regions.far_vertex, axis=1))
    away = mesh.vertices[mesh.faces[ring]].mean(axis=1) - mesh.vertices[regions.far_vertex]
    assert np.all(np.einsum("kj,kj->k", away, tx.face_direction[ring]) > 0)
    ring = np.flatnonzero(np.any(mesh.faces == regions.base_centre, axis=1))
    towards = mesh.vertices[regions.base_centre] - mesh.vertices[mesh.faces[ring]].mean(axis=1)
    assert np.all(np.einsum("kj,kj->k", towards, tx.face_direction[ring]) > 0)


def test_icosphere_indices():
    mesh = icosphere_mesh()
    assert_prescribed(mesh, detect_regions(RegionParams(up_axis="+z"), mesh, touch_of(mesh)))


def test_bone_indices():
    mesh, regions, *_ = prepared(str(sample_mesh_path("bone.ply")), 3000)
    assert_prescribed(mesh, regions)


SHARED = sorted(SHARED_MESHES.glob("*.ply")) if SHARED_MESHES.is_dir() else []


@pytest.mark.skipif(not SHARED, reason=f"no shared meshes in {SHARED_MESHES}")
@pytest.mark.parametrize("path", SHARED, ids=[p.stem for p in SHARED])
def test_shared_mesh_indices(path: Path):
    mesh, regions, *_ = prepared(str(path), 3000)
    assert_prescribed(mesh, regions)


def test_genus_is_named():
    torus = trimesh.creation.torus(major_radius=50.0, minor_radius=15.0)
    tables = build_tables(np.asarray(torus.vertices), np.asarray(torus.faces))
    with pytest.raises(UserError, match="genus 1"):
        genus_check(tables)


def test_open_mesh_is_rejected():
    sphere = icosphere_mesh()
    with pytest.raises(UserError, match="boundary or non-manifold"):
        build_tables(sphere.vertices, sphere.faces[1:])


def test_identical_output_for_identical_input():
    mesh, regions, tables, tx, _ = bunny()
    again = compute_field(build_tables(mesh.vertices.copy(), mesh.faces.copy()), "tx", regions)
    for name in ("connection_angle", "face_angle", "face_direction", "start_distance", "realized_index"):
        assert getattr(again, name).tobytes() == getattr(tx, name).tobytes()
