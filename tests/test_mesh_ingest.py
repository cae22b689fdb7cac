"""mesh.load / mesh.scale / mesh.repair / mesh.remesh / mesh.check_topology, called directly."""
from __future__ import annotations

import hashlib
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh

from retrotouch.graph.errors import UserError
from retrotouch.nodes.data.types import Mesh
from retrotouch.nodes.mesh.loading import LoadParams, ScaleParams, load_mesh, resolve_mesh_path, scale_mesh
from retrotouch.nodes.geometry.triangles import signed_volume
from retrotouch.nodes.mesh.repair import (
    RemeshParams, RepairParams, decimate_dense, flat_faces, remesh, remove_flat_faces, repair_mesh,
)
from retrotouch.nodes.mesh.topology import CheckTopologyParams, check_topology, keeps_closed_topology, topology_report

REPO = Path(__file__).resolve().parents[1]

SHARED_MESHES = REPO.parent / "shared" / "meshes"


def as_mesh(tm: trimesh.Trimesh, name: str = "test") -> Mesh:
    return Mesh(
        vertices=np.asarray(tm.vertices, dtype=np.float64),
        faces=np.asarray(tm.faces, dtype=np.int64),
        source=name,
    )


@pytest.fixture(scope="module")
def bunny() -> Mesh:
    return load_mesh(LoadParams())


def test_builtin_bunny_loads_with_content_hash(bunny: Mesh) -> None:
    path = resolve_mesh_path("builtin:bunny")
    assert bunny.vertices.shape == (28088, 3) and bunny.faces.shape == (56172, 3)
    assert bunny.vertices.dtype == np.float64 and bunny.faces.dtype == np.int64
    assert bunny.source == f"builtin:bunny sha256:{hashlib.sha256(path.read_bytes()).hexdigest()}"
    assert LoadParams().input_files() == [str(path)]


def test_units_convert_to_mm(tmp_path: Path) -> None:
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    path = tmp_path / "box.stl"
    box.export(path)
    mesh = load_mesh(LoadParams(path=str(path), units="in"))
    np.testing.assert_allclose(mesh.vertices.max(0) - mesh.vertices.min(0), [25.4, 50.8, 76.2])
    assert len(mesh.vertices) == 8  # STL triangle soup merged into a closed box


def test_glb_scene_is_flattened(tmp_path: Path) -> None:
    scene = trimesh.Scene(
        [trimesh.creation.box(extents=(1, 1, 1)), trimesh.creation.icosphere(radius=0.5).apply_translation((3, 0, 0))]
    )
    path = tmp_path / "scene.glb"
    scene.export(path)
    mesh = load_mesh(LoadParams(path=str(path), units="cm"))
    assert len(mesh.faces) == 12 + 1280
    np.testing.assert_allclose(mesh.vertices[:, 0].max(), 35.0, rtol=1e-6)


def test_content_change_changes_source_hash(tmp_path: Path) -> None:
    path = tmp_path / "shape.ply"
    trimesh.creation.box().export(path)
    first = load_mesh(LoadParams(path=str(path))).source
    trimesh.creation.icosphere().export(path)
    assert load_mesh(LoadParams(path=str(path))).source != first


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("empty.ply", b"", "is empty"),
        ("notamesh.obj", b"hello\nthis is a shopping list\n", "contains no triangles"),
        ("notamesh.stl", b"solid? no, just some words\n", "contains no triangles"),
        ("points.xyz", b"1 2 3\n4 5 6\n", "holds 2 points and no faces: a scan needs at least 100 points"),
        ("points.txt", b"1 2 3\n", "unsupported extension"),
        ("random.obj", np.random.default_rng(1).bytes(4000), "cannot read mesh file|contains no triangles"),
        ("random.stl", np.random.default_rng(2).bytes(4000), "cannot read mesh file|contains no triangles"),
    ],
)
def test_unreadable_files_give_one_line_errors(tmp_path: Path, name: str, content: bytes, message: str) -> None:
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(UserError, match=message) as info:
        load_mesh(LoadParams(path=str(path)))
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_truncated_ply(tmp_path: Path) -> None:
    data = trimesh.creation.icosphere().export(file_type="ply")
    path = tmp_path / "cut.ply"
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(UserError, match=r"cannot read mesh file .*cut\.ply.*export it again"):
        load_mesh(LoadParams(path=str(path)))


def test_obj_with_a_latin1_comment_loads(tmp_path: Path) -> None:
    path = tmp_path / "tetra.obj"
    path.write_bytes("# mod\xe8le de caf\xe9\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n".encode("latin-1"))
    mesh = load_mesh(LoadParams(path=str(path)))
    assert mesh.vertices.shape == (4, 3) and mesh.faces.shape == (4, 3)


def test_ply_face_index_out_of_range(tmp_path: Path) -> None:
    path = tmp_path / "bad.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n"
    )
    with pytest.raises(UserError, match=r"bad\.ply has faces with vertex indices outside 0\.\.2") as info:
        load_mesh(LoadParams(path=str(path)))
    assert "\n" not in str(info.value)


def test_nan_coordinates_give_one_line_and_no_warnings(tmp_path: Path) -> None:
    path = tmp_path / "nan.obj"
    path.write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(UserError, match="has NaN or infinite coordinates"):
            load_mesh(LoadParams(path=str(path)))
    assert not [w for w in caught if issubclass(w.category, RuntimeWarning)]


def test_folder_as_mesh_path(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="is a folder, not a file"):
        load_mesh(LoadParams(path=str(tmp_path)))


@pytest.mark.parametrize("suffix", [".ply", ".xyz"])
def test_point_cloud_with_holes_and_fragments_becomes_one_closed_genus_zero_mesh(tmp_path: Path, suffix: str) -> None:
    rng = np.random.default_rng(0)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=40.0)
    points = np.asarray(trimesh.sample.sample_surface_even(sphere, 6000, seed=0)[0])
    points = points[np.linalg.norm(points - [0.0, 0.0, 40.0], axis=1) > 12.0]  # a hole at the top
    fragment = rng.normal((90.0, 0.0, 0.0), 2.0, size=(80, 3))  # a loose cluster beside the object
    path = tmp_path / f"scan{suffix}"
    if suffix == ".xyz":
        np.savetxt(path, np.vstack([points, fragment]))
    else:
        trimesh.PointCloud(np.vstack([points, fragment])).export(path)
    loaded = load_mesh(LoadParams(path=str(path)))
    assert loaded.repairs and loaded.repairs[0].startswith(f"reconstructed a closed surface from {len(points) + 80:,} points")
    repaired = repair_mesh(RepairParams(), loaded)
    report = check_topology(CheckTopologyParams(), repaired)["report"]
    assert (report["components"], report["genus"], report["boundary_edges"]) == (1, 0, 0)
    assert any(line.startswith("dropped 1 loose fragment(s)") for line in repaired.repairs)
    radius = np.linalg.norm(repaired.vertices, axis=1)
    assert abs(np.median(radius) - 40.0) < 1.5 and radius.max() < 50.0  # the sphere, hole closed


def test_missing_file_and_unknown_builtin(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="does not exist"):
        load_mesh(LoadParams(path=str(tmp_path / "nope.obj")))
    with pytest.raises(UserError, match="unknown built-in mesh"):
        load_mesh(LoadParams(path="builtin:teapot"))


def test_scale_to_diagonal_is_exact(bunny: Mesh) -> None:
    scaled = scale_mesh(ScaleParams(diagonal_mm=170.0), bunny)
    diagonal = np.linalg.norm(scaled.vertices.max(0) - scaled.vertices.min(0))
    assert abs(diagonal - 170.0) / 170.0 < 1e-9
    factor = 170.0 / np.linalg.norm(bunny.vertices.max(0) - bunny.vertices.min(0))
    np.testing.assert_allclose(scaled.vertices, bunny.vertices * factor, rtol=1e-12)  # about the origin


def test_scale_longest_extent_about_bbox_centre(bunny: Mesh) -> None:
    scaled = scale_mesh(ScaleParams(longest_extent_mm=120.0, about="bbox_center"), bunny)
    extents = scaled.vertices.max(0) - scaled.vertices.min(0)
    assert abs(extents.max() - 120.0) < 1e-9
    centre = lambda v: 0.5 * (v.max(0) + v.min(0))  # noqa: E731
    np.testing.assert_allclose(centre(scaled.vertices), centre(bunny.vertices), atol=1e-12)


def test_scale_by_units_and_param_validation(bunny: Mesh) -> None:
    np.testing.assert_allclose(scale_mesh(ScaleParams(units="m"), bunny).vertices, bunny.vertices * 1000.0)
    with pytest.raises(ValueError, match="at most one of units, diagonal_mm, longest_extent_mm"):
        ScaleParams(units="m", diagonal_mm=100.0)
    sized = scale_mesh(ScaleParams(diagonal_mm=170.0), bunny)
    np.testing.assert_array_equal(scale_mesh(ScaleParams(), sized).vertices, sized.vertices)  # kept as loaded
    with pytest.raises(UserError, match=r"is 1 mm across \(bounding-box diagonal\) as loaded: .* check the file's units"):
        scale_mesh(ScaleParams(), bunny)  # unitless numbers kept as mm: too small for a table object


def test_a_gltf_scan_kept_at_its_size_is_told_that_gltf_stores_metres(tmp_path: Path) -> None:
    path = tmp_path / "mug_scan.glb"
    trimesh.creation.icosphere(subdivisions=2, radius=0.05).export(path)  # a 10 cm object, in metres
    loaded = load_mesh(LoadParams(path=str(path)))
    with pytest.raises(UserError, match=r"is 0\.173 mm across .* as loaded: .*; glTF stores metres: set units: m, or set"):
        scale_mesh(ScaleParams(), loaded)
    assert abs(np.ptp(load_mesh(LoadParams(path=str(path), units="m")).vertices[:, 0]) - 100.0) < 1e-4  # float32 in GLB
    ply = tmp_path / "mug_scan.ply"
    trimesh.creation.icosphere(subdivisions=2, radius=0.05).export(ply)
    with pytest.raises(UserError, match=r"as loaded: .*; check the file's units, or set"):  # other formats: no unit
        scale_mesh(ScaleParams(), load_mesh(LoadParams(path=str(ply))))


def test_a_file_in_metres_keeps_its_real_size_through_the_default_pipeline(tmp_path) -> None:
    """``-S units=m -S diagonal_mm=null``: a phone scan in metres arrives at its size in mm."""
    from retrotouch.graph.runner import make_plan

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.05)  # 100 mm across, in metres
    sphere.export(tmp_path / "ball.ply")
    overrides = [f"mesh={tmp_path / 'ball.ply'}", "units=m", "diagonal_mm=null"]
    plan = make_plan(str(REPO / "pipelines" / "retrofit.yaml"), overrides, str(tmp_path / "cache"))
    load, scale = (next(i for i in plan.instances if i.node == name) for name in ("load", "scaled"))
    mesh = scale_mesh(scale.params, load_mesh(load.params))
    assert np.ptp(mesh.vertices, axis=0) == pytest.approx([100.0] * 3, rel=0.01)


def test_sizes_no_table_object_has_are_refused_in_one_line(bunny: Mesh) -> None:
    """Below 10 mm or above 10 m across, from a parameter or from a file's units, the run stops at
    ingest with the size and what to check, before anything allocates per-object arrays."""
    for bad in (1e300, float("inf"), float("nan"), 1e12, 0.001):
        with pytest.raises(ValueError, match="diagonal_mm"):
            ScaleParams(diagonal_mm=bad)
    huge = as_mesh(trimesh.creation.icosphere(subdivisions=2, radius=1e7))
    with pytest.raises(UserError, match=r"3.46e\+10 mm across .* read in m: .*check the file's units"):
        scale_mesh(ScaleParams(units="m"), huge)
    tiny = as_mesh(trimesh.creation.icosphere(subdivisions=2, radius=1e-3))
    with pytest.raises(UserError, match=r"0.00[0-9]* mm across .* read in mm"):
        scale_mesh(ScaleParams(units="mm"), tiny)
    assert np.linalg.norm(np.ptp(scale_mesh(ScaleParams(diagonal_mm=10.0), bunny).vertices, axis=0)) == pytest.approx(10.0)


def test_remeshing_finer_than_a_million_vertices_is_refused_before_it_runs() -> None:
    sphere = as_mesh(trimesh.creation.icosphere(subdivisions=3, radius=40.0))  # 20,106 mm2
    with pytest.raises(UserError, match=r"target_edge_mm 0.001 would remesh .* raise target_edge_mm to at least 0.15"):
        remesh(RemeshParams(target_edge_mm=0.001), sphere)
    with pytest.raises(ValueError, match="target_vertices"):
        RemeshParams(target_vertices=100_000_000)


def test_non_finite_coordinates_fail_the_topology_check() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=40.0)
    vertices = sphere.vertices.copy()
    vertices[3] = np.nan
    with pytest.raises(UserError, match="NaN or infinite coordinates"):
        check_topology(CheckTopologyParams(), as_mesh(trimesh.Trimesh(vertices, sphere.faces, process=False)))


def test_repair_merges_duplicates_and_orients_outward() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=20.0)
    soup_vertices = sphere.vertices[sphere.faces].reshape(-1, 3)  # every face its own 3 vertices
    soup_faces = np.arange(len(soup_vertices)).reshape(-1, 3)[:, ::-1]  # and inward
    broken = Mesh(vertices=soup_vertices, faces=soup_faces, source="soup")
    repaired = repair_mesh(RepairParams(), broken)
    assert len(repaired.vertices) == len(sphere.vertices)
    assert signed_volume(repaired.vertices, repaired.faces) > 0
    check_topology(CheckTopologyParams(), repaired)


def test_repair_closes_holes_and_keeps_largest() -> None:
    big = trimesh.creation.icosphere(subdivisions=3, radius=20.0)
    small = trimesh.creation.icosphere(subdivisions=1, radius=2.0).apply_translation((50, 0, 0))
    both = trimesh.util.concatenate([big, small])
    holed = Mesh(np.asarray(both.vertices), np.asarray(both.faces[3:], dtype=np.int64), "holed")
    repaired = repair_mesh(RepairParams(keep_largest=True), holed)
    report = check_topology(CheckTopologyParams(), repaired)["report"]
    assert report["components"] == 1 and report["boundary_edges"] == 0
    assert report["vertices"] == len(big.vertices)


def test_scan_with_an_open_bottom_is_closed_by_default() -> None:
    """A turntable scan has no bottom: a hole with 1,500 boundary edges (more than any fixed small
    limit) is closed by the default repair, and a set limit still leaves it open."""
    tube = trimesh.creation.cylinder(radius=40.0, height=60.0, sections=1500)
    walls = np.asarray(tube.faces[tube.face_normals[:, 2] > -0.99], dtype=np.int64)
    scan = Mesh(np.asarray(tube.vertices), walls, "scan")
    repaired = repair_mesh(RepairParams(), scan)
    assert check_topology(CheckTopologyParams(), repaired)["report"]["genus"] == 0
    assert "closed 1 hole(s) with 1,498 faces" in repaired.repairs
    limited = repair_mesh(RepairParams(max_hole_edges=1000), scan)
    with pytest.raises(UserError, match="1500 boundary edges"):
        check_topology(CheckTopologyParams(), limited)


def test_remesh_to_vertex_count_lands_within_15_percent() -> None:
    sphere = as_mesh(trimesh.creation.icosphere(subdivisions=4, radius=40.0))
    out = remesh(RemeshParams(target_vertices=1000), sphere)
    assert abs(len(out.vertices) - 1000) / 1000 < 0.15
    assert out.vertices.flags.c_contiguous and out.faces.dtype == np.int64
    assert signed_volume(out.vertices, out.faces) > 0
    assert check_topology(CheckTopologyParams(), out)["report"]["genus"] == 0


def test_dense_input_is_decimated_before_remeshing() -> None:
    dense = as_mesh(trimesh.creation.icosphere(subdivisions=6, radius=40.0))  # 81,920 faces
    out = remesh(RemeshParams(target_vertices=1000), dense)
    assert out.repairs[0].startswith("decimated a dense input from 81,920 to 4,000 faces")
    assert abs(len(out.vertices) - 1000) / 1000 < 0.15
    assert check_topology(CheckTopologyParams(), out)["report"]["genus"] == 0


def test_a_cloud_denser_than_the_poisson_grid_is_thinned_first() -> None:
    from retrotouch.nodes.mesh.reconstruct import POINTS_PER_DEPTH_CELL, reconstruct_from_points

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=40.0)
    points = np.asarray(trimesh.sample.sample_surface_even(sphere, 60000, seed=0)[0])
    assert len(points) > POINTS_PER_DEPTH_CELL * 4**5
    surface = reconstruct_from_points(points, 5, "cloud")
    assert surface.stride == -(-len(points) // (POINTS_PER_DEPTH_CELL * 4**5)) > 1 and surface.strays == 0
    vertices, faces = surface.vertices, surface.faces
    report = topology_report(vertices, faces)
    assert (report["components"], report["genus"], report["boundary_edges"]) == (1, 0, 0)
    radius = np.linalg.norm(vertices, axis=1)
    assert np.abs(radius - 40.0).max() < 1.0  # a 2.5 mm grid cell: the surface stays on the sphere


def test_a_stray_point_far_from_the_scan_is_dropped_before_the_reconstruction(tmp_path: Path) -> None:
    from retrotouch.nodes.mesh.reconstruct import reconstruct_from_points

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=40.0)
    points = np.asarray(trimesh.sample.sample_surface_even(sphere, 6000, seed=0)[0])
    strays = np.array([[500.0, 0.0, 0.0], [0.0, -300.0, 200.0]])  # a reflection, a point of the room
    clean = reconstruct_from_points(points, 6, "cloud")
    with_strays = reconstruct_from_points(np.vstack([points, strays]), 6, "cloud")
    assert (clean.strays, with_strays.strays) == (0, 2)
    np.testing.assert_array_equal(with_strays.faces, clean.faces)  # the octree spans the object alone: same resolution
    np.testing.assert_allclose(with_strays.vertices, clean.vertices)
    path = tmp_path / "scan.xyz"
    np.savetxt(path, np.vstack([points, strays]))
    assert ", 2 stray point(s) far from the rest dropped" in load_mesh(LoadParams(path=str(path), poisson_depth=6)).repairs[0]


def test_decimation_keeps_a_genus_one_scan_genus_one() -> None:
    torus = trimesh.creation.torus(major_radius=40.0, minor_radius=12.0, major_sections=256, minor_sections=160)  # 81,920 faces
    vertices, faces, note = decimate_dense(np.asarray(torus.vertices), np.asarray(torus.faces, dtype=np.int64), 2000)
    assert note == "decimated a dense input from 81,920 to 4,000 faces before remeshing"
    report = topology_report(vertices, faces)
    assert (report["genus"], report["components"], report["boundary_edges"], report["non_manifold_vertices"]) == (1, 1, 0, 0)


def test_a_fast_collapse_that_changes_the_topology_is_replaced(monkeypatch: pytest.MonkeyPatch) -> None:
    """The fast collapse's result with a face missing (a hole) is not kept: the topology-keeping one runs."""
    import fast_simplification

    collapse = fast_simplification.simplify
    monkeypatch.setattr(fast_simplification, "simplify", lambda v, f, **kw: (lambda r: (r[0], r[1][1:]))(collapse(v, f, **kw)))
    dense = trimesh.creation.icosphere(subdivisions=6, radius=40.0)
    vertices, faces, note = decimate_dense(np.asarray(dense.vertices), np.asarray(dense.faces, dtype=np.int64), 2000)
    assert note.endswith("(the topology-keeping collapse: the fast one changed the surface's topology)")
    report = topology_report(vertices, faces)
    assert (report["genus"], report["boundary_edges"], len(faces)) == (0, 0, 4000)


def test_closed_topology_check_refuses_every_change() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=20.0)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces, dtype=np.int64)
    torus = trimesh.creation.torus(major_radius=20.0, minor_radius=6.0)
    assert keeps_closed_topology(v, f, v, f)
    assert not keeps_closed_topology(v, f, v, f[1:])  # a hole
    assert not keeps_closed_topology(v, f, v, f[:, ::-1])  # turned inside out
    assert not keeps_closed_topology(v, f, np.r_[v, v + 100.0], np.r_[f, f + len(v)])  # two components
    assert not keeps_closed_topology(v, f, np.asarray(torus.vertices), np.asarray(torus.faces, dtype=np.int64))  # a handle


def test_missed_vertex_target_is_logged_and_listed(caplog: pytest.LogCaptureFixture) -> None:
    coarse = as_mesh(trimesh.creation.icosphere(subdivisions=1, radius=40.0))
    with caplog.at_level("WARNING"):
        out = remesh(RemeshParams(target_vertices=20000, iterations=1, max_passes=1), coarse)
    assert out.repairs[-1].startswith(f"remeshing missed its target: {len(out.vertices):,} vertices for 20,000")
    assert "remeshing missed its target" in caplog.text


def test_repairs_are_listed() -> None:
    big = trimesh.creation.icosphere(subdivisions=3, radius=20.0)
    inward = Mesh(np.asarray(big.vertices), np.asarray(big.faces[1:, ::-1], dtype=np.int64), "holed", ("earlier step",))
    repaired = repair_mesh(RepairParams(), inward)
    assert repaired.repairs[0] == "earlier step"
    assert repaired.repairs[1] == "closed 1 hole(s) with 1 faces"
    assert repaired.repairs[-1] == "flipped the faces to point outward"


def test_remesh_to_edge_length() -> None:
    sphere = as_mesh(trimesh.creation.icosphere(subdivisions=3, radius=40.0))
    out = remesh(RemeshParams(target_edge_mm=6.0), sphere)
    edges = out.vertices[out.faces] - out.vertices[np.roll(out.faces, -1, axis=1)]
    assert abs(np.median(np.linalg.norm(edges, axis=2)) - 6.0) < 1.0


def test_remeshing_stays_on_the_input_surface_and_keeps_its_creases() -> None:
    box = trimesh.creation.box(extents=(80.0, 50.0, 30.0))
    out = remesh(RemeshParams(target_vertices=2000), as_mesh(box))
    remeshed = trimesh.Trimesh(out.vertices, out.faces, process=False)
    points, _ = trimesh.sample.sample_surface(remeshed, 20000, seed=1)
    assert np.abs(trimesh.proximity.signed_distance(box, points)).max() < 0.05  # mm: faces lie on the box
    assert remeshed.volume == pytest.approx(box.volume, rel=1e-3)  # corners and edges kept, none cut off


def test_remesh_params_need_one_target() -> None:
    with pytest.raises(ValueError, match="exactly one"):
        RemeshParams()


def test_check_topology_passes_good_mesh(bunny: Mesh) -> None:
    out = check_topology(CheckTopologyParams(), bunny)
    assert out["mesh"] is bunny
    report = out["report"]
    assert (report["genus"], report["euler_characteristic"], report["components"]) == (0, 2, 1)
    assert report["boundary_edges"] == report["non_manifold_edges"] == 0


def test_open_box_reports_boundary() -> None:
    box = trimesh.creation.box(extents=(10, 10, 10))
    mesh = Mesh(np.asarray(box.vertices), np.asarray(box.faces[2:], dtype=np.int64), "box.ply sha256:00")
    with pytest.raises(UserError, match=r"^box\.ply: 4 boundary edges \(1 hole\(s\)\) left open: add mesh.repair"):
        check_topology(CheckTopologyParams(), mesh)


def test_torus_reports_genus_one() -> None:
    with pytest.raises(UserError, match="genus 1: the layout method needs a genus-0 surface"):
        check_topology(CheckTopologyParams(), as_mesh(trimesh.creation.torus(30.0, 10.0), "torus"))
    assert check_topology(CheckTopologyParams(expected_genus=1), as_mesh(trimesh.creation.torus(30.0, 10.0)))


def test_two_spheres_report_components() -> None:
    a = trimesh.creation.icosphere(radius=10.0)
    b = trimesh.creation.icosphere(radius=10.0).apply_translation((50, 0, 0))
    with pytest.raises(UserError, match=r"2 components: add mesh.repair \(keep_largest: true keeps the largest\)"):
        check_topology(CheckTopologyParams(), as_mesh(trimesh.util.concatenate([a, b])))


def test_inward_faces_and_non_manifold_edge() -> None:
    sphere = trimesh.creation.icosphere(radius=10.0)
    inward = Mesh(np.asarray(sphere.vertices), np.asarray(sphere.faces[:, ::-1], dtype=np.int64), "in")
    with pytest.raises(UserError, match="faces point inward"):
        check_topology(CheckTopologyParams(), inward)
    fin = np.vstack([sphere.vertices, [[0.0, 0.0, 30.0]]])
    a, b = sphere.faces[0, :2]
    faces = np.vstack([sphere.faces, [[a, b, len(fin) - 1]]])
    with pytest.raises(UserError, match="1 non-manifold edges"):
        check_topology(CheckTopologyParams(), Mesh(fin, faces.astype(np.int64), "fin"))


@pytest.mark.parametrize("name", [
    "blub_fish.ply", "duck_gao.ply", "pear_gao.ply", "penguin_oded.ply",
    "spoon_pfc.ply", "spot_crane.ply", "teddy1_gao.ply",
])
def test_shared_meshes_load_as_genus_zero(name: str) -> None:
    path = SHARED_MESHES / name
    if not path.is_file():
        pytest.skip(f"{path} absent (shared test meshes are not checked out next to the repo)")
    mesh = scale_mesh(ScaleParams(diagonal_mm=150.0), load_mesh(LoadParams(path=str(path))))
    report = check_topology(CheckTopologyParams(), mesh)["report"]
    assert report["genus"] == 0 and report["components"] == 1 and report["boundary_edges"] == 0


def test_noisy_dense_scan_is_decimated_and_remeshed_to_its_target() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=6, radius=40.0)  # 81,920 faces
    noisy = sphere.vertices + np.random.default_rng(0).normal(scale=0.3, size=sphere.vertices.shape)
    out = remesh(RemeshParams(target_vertices=1000), Mesh(np.asarray(noisy), np.asarray(sphere.faces, dtype=np.int64), "scan"))
    assert abs(len(out.vertices) - 1000) / 1000 <= 0.10, len(out.vertices)
    assert out.repairs[0].startswith("decimated a dense input from 81,920 to 4,000 faces")
    assert check_topology(CheckTopologyParams(), out)["report"]["genus"] == 0


@pytest.mark.parametrize("seed", [1, 2, 6])
def test_stray_facets_sharing_tips_are_repaired_away_round_by_round(seed: int) -> None:
    """Facets hanging off a sphere's edges, several sharing a tip outside it (a scan's stray facets):
    removing the faces of the non-manifold edges leaves non-manifold vertices, and splitting those
    leaves new ones for a round or two; repair goes on until none is left, and one closed genus-0
    surface remains (one round left non-manifold vertices, which the topology check refused)."""
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=40.0)
    rng = np.random.default_rng(seed)
    vertices = list(sphere.vertices)
    tips = []
    for _ in range(rng.integers(1, 4)):
        tips.append(len(vertices))
        vertices.append(sphere.vertices[rng.integers(len(sphere.vertices))] * 1.5)
    facets = [[a, b, tips[rng.integers(len(tips))] if rng.random() < 0.7 else rng.integers(len(sphere.vertices))]
              for a, b in sphere.edges_unique[rng.choice(len(sphere.edges_unique), rng.integers(2, 10), replace=False)]]
    mesh = Mesh(np.array(vertices), np.vstack([sphere.faces, facets]).astype(np.int64), "facets")
    assert topology_report(mesh.vertices, mesh.faces)["non_manifold_edges"] > 0
    repaired = repair_mesh(RepairParams(), mesh)
    report = check_topology(CheckTopologyParams(), repaired)["report"]
    assert (report["components"], report["genus"], report["boundary_edges"]) == (1, 0, 0)


def assert_manifold_and_oriented(vertices: np.ndarray, faces: np.ndarray) -> None:
    report = topology_report(vertices, faces)
    assert report["boundary_edges"] == report["non_manifold_edges"] == report["non_manifold_vertices"] == 0
    assert report["inconsistent_edges"] == 0 and report["components"] == 1 and report["signed_volume_mm3"] > 0


def test_non_manifold_vertices_repair_cannot_remove_are_rebuilt_from_samples() -> None:
    """Twenty facets hanging off a sphere's edges, all sharing one tip: every round of repair leaves
    one non-manifold vertex, so the surface is rebuilt from points sampled on it, and the repair says why."""
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=40.0)
    rng = np.random.default_rng(0)
    tip = len(sphere.vertices)
    edges = sphere.edges_unique[rng.choice(len(sphere.edges_unique), 20, replace=False)]
    facets = np.column_stack([edges, np.full(len(edges), tip)])
    mesh = Mesh(np.vstack([sphere.vertices, 1.5 * sphere.vertices[:1]]), np.vstack([sphere.faces, facets]), "fan")
    repaired = repair_mesh(RepairParams(rebuild_depth=5), mesh)
    assert any(re.match(r"rebuilt the surface from 24,576 points sampled on it \(screened Poisson, depth 5, within "
                        r"[\d.]+ mm of it at nine vertices in ten\): repair left 1 non-manifold vertices", line)
               for line in repaired.repairs)
    assert_manifold_and_oriented(repaired.vertices, repaired.faces)
    assert_near_the_input(repaired, mesh, depth=5)


def assert_near_the_input(repaired: Mesh, given: Mesh, depth: int) -> None:
    """Nine in ten vertices of the rebuilt surface lie within one cell of the Poisson grid (the longest
    side of the input's box over ``2**depth``) of the input surface."""
    cell = float(np.ptp(given.vertices, axis=0).max()) / 2**depth
    distance = trimesh.Trimesh(given.vertices, given.faces, process=False).nearest.on_surface(repaired.vertices)[1]
    assert np.percentile(distance, 90) < cell


def klein_bottle(sections: int = 48, around: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """The figure-8 immersion of a Klein bottle (radius 40 mm): closed, manifold, not orientable.
    Grid point (i, j) of ``u = 2 pi i / sections``, ``v = 2 pi j / around``; going once round u
    returns to (0, -j), the gluing that makes it one-sided."""
    u, v = np.meshgrid(2 * np.pi * np.arange(sections) / sections, 2 * np.pi * np.arange(around) / around, indexing="ij")
    tube = np.cos(u / 2) * np.sin(v) - np.sin(u / 2) * np.sin(2 * v)
    points = np.stack([(30 + 10 * tube) * np.cos(u), (30 + 10 * tube) * np.sin(u),
                       10 * (np.sin(u / 2) * np.sin(v) + np.cos(u / 2) * np.sin(2 * v))], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(sections), np.arange(around), indexing="ij")
    index = lambda a, b: np.where(a == sections, (-b) % around, a * around + b % around)  # noqa: E731
    a, b, c, d = index(i, j), index(i + 1, j), index(i + 1, j + 1), index(i, j + 1)
    return points, np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])


def test_a_surface_whose_faces_cannot_be_oriented_alike_is_rebuilt_from_samples() -> None:
    vertices, faces = klein_bottle()
    assert topology_report(vertices, faces)["boundary_edges"] == 0  # closed, and one-sided:
    assert topology_report(vertices, faces)["inconsistent_edges"] > 0
    bottle = Mesh(vertices, faces, "klein.obj")
    repaired = repair_mesh(RepairParams(rebuild_depth=6), bottle)
    assert any(line.startswith("rebuilt the surface") and "edges whose faces cannot be oriented alike" in line
               for line in repaired.repairs)
    assert_manifold_and_oriented(repaired.vertices, repaired.faces)
    assert_near_the_input(repaired, bottle, depth=6)


def test_remeshing_flips_away_a_face_whose_vertex_lies_on_its_opposite_edge() -> None:
    """A closed mesh with one vertex moved onto the edge opposite it (three corners in a line, as the
    remesher can leave at a crease): the topology check refuses its zero-area face in one line, and
    the edge flip that mesh.remesh applies removes it without touching a vertex or the topology."""
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=40.0)
    vertices, faces = np.array(sphere.vertices), np.asarray(sphere.faces, dtype=np.int64)
    a, b, c = faces[0]
    vertices[c] = 0.5 * (vertices[a] + vertices[b])
    with pytest.raises(UserError, match=r"^flat: 1 faces of zero area: remesh to another vertex count"):
        check_topology(CheckTopologyParams(), Mesh(vertices, faces, "flat"))
    flipped_vertices, flipped_faces, removed = remove_flat_faces(vertices, faces)
    assert removed >= 1 and not flat_faces(flipped_vertices, flipped_faces).any()
    np.testing.assert_array_equal(flipped_vertices, vertices)
    assert len(flipped_faces) == len(faces) and np.count_nonzero(np.any(flipped_faces != faces, axis=1)) == 2
    report = check_topology(CheckTopologyParams(), Mesh(flipped_vertices, flipped_faces, "flipped"))["report"]
    assert (report["genus"], report["zero_area_faces"]) == (0, 0)


def test_a_pinch_vertex_split_by_repair_stays_split_after_remeshing() -> None:
    """A capsule bent round until its two poles meet, welded there into one non-manifold vertex (a
    scan where two parts of the surface touch): repair splits it, and remeshing must not weld the two
    copies into a pinch again, so the mesh passes the topology check as a sphere."""
    capsule = trimesh.creation.capsule(height=100.0, radius=10.0, count=[32, 32])
    v, f = np.asarray(capsule.vertices, dtype=np.float64), np.asarray(capsule.faces, dtype=np.int64)
    phi = (v[:, 2] - v[:, 2].min()) / np.ptp(v[:, 2]) * 2.0 * np.pi
    bend = np.ptp(v[:, 2]) / (2.0 * np.pi) + v[:, 0]
    bent = np.column_stack([bend * np.cos(phi), bend * np.sin(phi), v[:, 1]])
    welded = np.where(f == np.argmax(v[:, 2]), np.argmin(v[:, 2]), f)
    used, welded = np.unique(welded, return_inverse=True)
    pinched = Mesh(bent[used], welded.reshape(-1, 3).astype(np.int64), "pinched")
    assert topology_report(pinched.vertices, pinched.faces)["non_manifold_vertices"] == 1
    repaired = repair_mesh(RepairParams(), pinched)
    assert "moved apart the 2 copies of split non-manifold vertices, so remeshing keeps them apart" in repaired.repairs
    out = remesh(RemeshParams(target_vertices=3000), repaired)
    report = topology_report(out.vertices, out.faces)
    assert report["non_manifold_vertices"] == 0 and report["euler_characteristic"] == 2 and report["boundary_edges"] == 0


def test_a_single_triangle_is_refused_as_an_open_flat_sheet_not_as_holes_to_close() -> None:
    """A lone triangle has one boundary loop that mesh.repair cannot close (the patch would repeat
    the face): the check says it is a flat sheet, not that holes should be closed by the repair that
    already ran."""
    triangle = Mesh(np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 100.0, 0.0]]),
                    np.array([[0, 1, 2]], dtype=np.int64), "triangle.obj")
    repaired = remesh(RemeshParams(target_vertices=500), repair_mesh(RepairParams(), triangle))
    with pytest.raises(UserError, match=r"triangle.obj: the surface is an open flat sheet \(\d+ boundary edges, every "
                       r"point in one plane\), not a solid object: give it its thickness") as error:
        check_topology(CheckTopologyParams(), repaired)
    assert "close_holes" not in str(error.value)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=50.0)
    bowl = Mesh(sphere.vertices, sphere.faces[sphere.triangles_center[:, 2] < 20.0], "open_bowl.obj")  # a curved open scan
    with pytest.raises(UserError, match=r"\d+ boundary edges \(1 hole\(s\)\) left open"):
        check_topology(CheckTopologyParams(), bowl)


def test_a_flat_outline_closed_into_a_double_sheet_is_refused_as_no_solid() -> None:
    """A 2D outline exported as a mesh (every vertex at z = 0) whose open side mesh.repair closes with
    a coplanar patch is closed, manifold and genus 0 but encloses nothing: one line says so."""
    disc = trimesh.creation.annulus(r_min=0.0, r_max=40.0, height=1.0, sections=48)
    top = disc.vertices[:, 2] > 0
    keep = np.flatnonzero(top)
    faces = disc.faces[np.all(top[disc.faces], axis=1)]
    flat = np.column_stack([disc.vertices[keep, :2], np.zeros(len(keep))])
    faces = np.searchsorted(keep, faces)
    sheet = repair_mesh(RepairParams(), Mesh(flat, faces.astype(np.int64), "outline.obj"))
    assert any(line.startswith("closed 1 hole(s)") for line in sheet.repairs)
    with pytest.raises(UserError, match=r"outline.obj: the surface encloses no volume .*flat sheet, not a solid object"):
        check_topology(CheckTopologyParams(), sheet)
    solid = as_mesh(trimesh.creation.box(extents=(80.0, 80.0, 0.5)))  # a thin but real slab passes
    assert check_topology(CheckTopologyParams(), solid)["report"]["mean_thickness_mm"] > 0.2


def noisy_sphere() -> tuple[np.ndarray, np.ndarray]:
    """20,000 points of a 50 mm sphere with 4 % (2 mm) radial noise, and their outward unit normals."""
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(20000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return directions * rng.normal(1.0, 0.04, size=(20000, 1)) * 50.0, directions


def test_a_noisy_cloud_is_reconstructed_coarser_until_it_has_no_spurious_handle(tmp_path: Path) -> None:
    """A sphere sampled with strong radial noise (the normal estimate flips here and there): depth 7
    closes handles through the surface, a coarser octree does not; a real handle stays and is refused
    in one line that says the surface came from points."""
    from retrotouch.nodes.mesh.reconstruct import reconstruct_from_points

    noisy, _ = noisy_sphere()
    surface = reconstruct_from_points(noisy, 7, "cloud")
    assert surface.handles and min(surface.handles.values()) > 0 and surface.depth < 7
    assert topology_report(surface.vertices, surface.faces)["genus"] == 0
    path = tmp_path / "noisy.xyz"
    np.savetxt(path, noisy)
    mesh = load_mesh(LoadParams(path=str(path)))
    assert f"(screened Poisson, depth {surface.depth}, estimated normals; depth 7 with estimated normals gave" \
        in mesh.repairs[0]
    torus = trimesh.creation.torus(major_radius=40.0, minor_radius=15.0)
    ring = tmp_path / "ring.xyz"
    np.savetxt(ring, trimesh.sample.sample_surface_even(torus, 8000, seed=0)[0])
    loaded = load_mesh(LoadParams(path=str(ring), poisson_depth=6))
    assert "depth 5" in loaded.repairs[0]  # tried coarser: the handle is real
    with pytest.raises(UserError, match=r"genus 1 as reconstructed from the scan's points at every octree depth tried"):
        check_topology(CheckTopologyParams(), loaded)


def test_a_scan_s_own_normals_are_tried_when_estimated_ones_give_a_handle(tmp_path: Path) -> None:
    """The noisy sphere, whose estimated normals give handles at depth 7, is reconstructed there with
    the file's outward unit normals (PLY nx ny nz); normals a tool left unoriented (random signs)
    give handles too, so the reconstruction goes coarser; an XYZ file's colour columns are not normals."""
    points, normals = noisy_sphere()
    oriented = tmp_path / "oriented.ply"
    header = ("ply\nformat ascii 1.0\nelement vertex %d\nproperty float x\nproperty float y\nproperty float z\n"
              "property float nx\nproperty float ny\nproperty float nz\nend_header\n" % len(points))
    oriented.write_text(header + "\n".join(" ".join(f"{v:.6f}" for v in row) for row in np.hstack([points, normals])))
    assert "(screened Poisson, depth 7, the file's normals; depth 7 with estimated normals gave" \
        in load_mesh(LoadParams(path=str(oriented))).repairs[0]
    signs = np.where(np.random.default_rng(1).random(len(points)) < 0.5, -1.0, 1.0)[:, None]
    unoriented = tmp_path / "unoriented.xyz"
    np.savetxt(unoriented, np.hstack([points, normals * signs]))
    repairs = load_mesh(LoadParams(path=str(unoriented))).repairs[0]
    assert "estimated normals; depth 7 with estimated normals gave" in repairs and "depth 7 with the file's normals gave" in repairs
    coloured = tmp_path / "coloured.xyz"
    np.savetxt(coloured, np.hstack([points, np.full((len(points), 3), 200.0)]))
    assert "the file's normals" not in load_mesh(LoadParams(path=str(coloured))).repairs[0]


def test_a_one_sided_sheet_whose_rebuild_is_a_blob_is_refused_in_one_line() -> None:
    """A Moebius strip (a one-sided sheet without thickness, 30 mm wide): the surface rebuilt from its
    samples is a solid band round it, far from the sheet, so repair refuses it and says what to do."""
    sections, across = 96, 6
    u, w = np.meshgrid(2 * np.pi * np.arange(sections) / sections, np.linspace(-15.0, 15.0, across), indexing="ij")
    points = np.stack([(40 + w * np.cos(u / 2)) * np.cos(u), (40 + w * np.cos(u / 2)) * np.sin(u), w * np.sin(u / 2)],
                      axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(sections), np.arange(across - 1), indexing="ij")
    index = lambda a, b: np.where(a == sections, across - 1 - b, a * across + b)  # noqa: E731 (the half twist)
    a, b, c, d = index(i, j), index(i + 1, j), index(i + 1, j + 1), index(i, j + 1)
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    with pytest.raises(UserError, match=r"^mobius.obj: repair left \d+ edges whose faces cannot be oriented alike, and "
                       r"the surface rebuilt from samples of it strays [\d.]+ mm from it .* make it one closed, manifold "
                       r"surface in a mesh editor, or export the parts as one solid$"):
        repair_mesh(RepairParams(rebuild_depth=6), Mesh(points, faces, "mobius.obj"))
