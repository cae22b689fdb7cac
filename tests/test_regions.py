"""regions.detect on the bunny (170 mm diagonal), a sphere, the shared meshes and generated shapes,
called directly."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import trimesh

import shapes
from touch_fixture import touch_of
from retrotouch.graph.errors import UserError
from retrotouch.nodes.data.types import Mesh, SurfaceRegions
from retrotouch.nodes.geometry.triangles import corners, normals
from retrotouch.nodes.mesh.loading import LoadParams, ScaleParams, load_mesh, scale_mesh
from retrotouch.nodes.mesh.repair import RemeshParams, remesh
from retrotouch.nodes.regions import detect
from retrotouch.nodes.regions.base import is_sheet
from retrotouch.nodes.regions.detect import RegionParams, detect_regions, parse_axis
from retrotouch.nodes.regions.faces import FaceGraph

SHARED_MESHES = Path(__file__).resolve().parents[1].parent / "shared" / "meshes"


@pytest.fixture(scope="module")
def bunny() -> Mesh:
    return scale_mesh(ScaleParams(diagonal_mm=170.0), load_mesh(LoadParams()))


@pytest.fixture(scope="module")
def bunny_regions(bunny: Mesh) -> SurfaceRegions:
    return detect_regions(RegionParams(), bunny, touch_of(bunny))


@pytest.fixture(scope="module")
def sphere() -> Mesh:
    tm = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    return Mesh(np.asarray(tm.vertices, dtype=np.float64), np.asarray(tm.faces, dtype=np.int64), "sphere")


def vertex_faces(mesh: Mesh, vertex: int) -> np.ndarray:
    return np.flatnonzero((mesh.faces == vertex).any(axis=1))


def test_bunny_rests_on_its_bottom(bunny: Mesh, bunny_regions: SurfaceRegions) -> None:
    assert "wiring" not in bunny_regions.pose_reason  # its foot ring's rim has room for the wiring
    r = bunny_regions
    assert abs(np.linalg.norm(r.up) - 1.0) < 1e-12
    assert r.up[1] > 0.99  # pymeshlab's bunny stands on -y
    face_normals, areas = normals(corners(bunny.vertices, bunny.faces))
    mean_normal = (face_normals[r.base_faces] * areas[r.base_faces, None]).sum(0)
    assert mean_normal @ r.up / np.linalg.norm(mean_normal) < -0.95  # base faces point down
    share = areas[r.base_faces].sum() / areas.sum()
    assert 0.03 < share < 0.2, share
    height = bunny.vertices @ r.up
    base_height = height[np.unique(bunny.faces[r.base_faces])]
    assert base_height.max() - height.min() < 0.05 * np.ptp(height)  # on the support plane


def test_masks_partition_the_faces(bunny_regions: SurfaceRegions) -> None:
    r = bunny_regions
    stacked = np.stack([r.base_faces, r.exclusion_base, r.exclusion_far, r.sensing_faces]).astype(int)
    assert (stacked.sum(axis=0) == 1).all()
    assert r.exclusion_base.any() and r.exclusion_far.any() and r.sensing_faces.sum() > 0.7 * len(r.sensing_faces)


def test_base_centre_and_dipole(bunny: Mesh, bunny_regions: SurfaceRegions) -> None:
    r = bunny_regions
    assert r.base_faces[vertex_faces(bunny, r.base_centre)].all()  # interior base vertex
    a, b = (int(v) for v in r.base_dipole)
    assert a == r.base_centre and a != b
    edges = {tuple(e) for e in np.sort(np.stack([bunny.faces, np.roll(bunny.faces, -1, 1)], 2).reshape(-1, 2), 1)}
    assert (min(a, b), max(a, b)) in edges
    assert r.base_faces[vertex_faces(bunny, b)].all()
    assert r.base_dipole.dtype == np.int64 and r.base_dipole.shape == (2,)
    # the centre is deep inside: farther from the non-base surface than most base vertices
    base_vertices = np.unique(bunny.faces[r.base_faces])
    gap = np.linalg.norm(bunny.vertices[np.unique(bunny.faces[~r.base_faces])][:, None] - bunny.vertices[a], axis=2).min()
    assert gap > 10.0, gap
    assert len(base_vertices) > 1000


def test_far_vertex_is_the_ear_or_head(bunny: Mesh, bunny_regions: SurfaceRegions) -> None:
    r = bunny_regions
    height = bunny.vertices @ r.up
    assert height[r.far_vertex] > height.min() + 0.85 * np.ptp(height)
    assert r.base_distance_mm[r.far_vertex] > 110.0
    assert r.exclusion_far[vertex_faces(bunny, r.far_vertex)].all()
    assert r.base_distance_mm[np.unique(bunny.faces[r.base_faces])].max() < 1e-6


def test_exclusion_regions_respect_their_radii(bunny: Mesh, bunny_regions: SurfaceRegions) -> None:
    r = bunny_regions
    params = RegionParams()
    assert r.base_distance_mm[bunny.faces[r.exclusion_base]].mean(axis=1).max() < params.exclusion_base_mm
    far_point = bunny.vertices[r.far_vertex]
    chord = np.linalg.norm(bunny.vertices[bunny.faces[r.exclusion_far]] - far_point, axis=2).mean(axis=1)
    assert chord.max() < params.exclusion_far_mm + 2.0  # geodesic radius bounds the chord (+ one edge)


def test_base_boundary_edges_separate_sensing_from_base(bunny: Mesh, bunny_regions: SurfaceRegions) -> None:
    r = bunny_regions
    edges = r.base_boundary_edges
    assert edges.dtype == np.int64 and edges.shape[1] == 2 and len(edges) > 50
    halfedges = np.stack([bunny.faces, np.roll(bunny.faces, -1, 1)], 2).reshape(-1, 2)
    lookup = {tuple(h): i // 3 for i, h in enumerate(halfedges)}
    blocked = r.base_faces | r.exclusion_base
    for a, b in edges:
        assert r.sensing_faces[lookup[(a, b)]] and blocked[lookup[(b, a)]]
    # closed loops: every vertex is entered as often as it is left
    assert np.array_equal(np.bincount(edges[:, 0], minlength=len(bunny.vertices)),
                          np.bincount(edges[:, 1], minlength=len(bunny.vertices)))


def test_up_axis_override(bunny: Mesh) -> None:
    r = detect_regions(RegionParams(up_axis="+z", exclusion_base_mm=0.0, wiring_room_mm=0.0), bunny, touch_of(bunny))
    np.testing.assert_allclose(r.up, [0.0, 0.0, 1.0])
    z = bunny.vertices[:, 2]
    assert r.base_faces[vertex_faces(bunny, int(np.argmin(z)))].any()  # holds the lowest point
    assert r.tipping_angle_deg < 0 and "up_axis +z given" in r.pose_reason  # the bunny would fall over
    assert z[np.unique(bunny.faces[r.base_faces])].max() <= z.min() + 0.25 * np.ptp(z)  # low side
    assert r.base_faces[vertex_faces(bunny, r.base_centre)].all()
    assert not r.exclusion_base.any()


def test_seed_point_and_angle_overrides(bunny: Mesh, bunny_regions: SurfaceRegions) -> None:
    seed_face = int(np.flatnonzero(bunny_regions.base_faces)[0])
    seed_point = tuple(bunny.vertices[bunny.faces[seed_face]].mean(axis=0))
    by_point = detect_regions(RegionParams(seed_point=seed_point, up_axis=tuple(bunny_regions.up)), bunny, touch_of(bunny))
    assert by_point.base_faces[seed_face]
    by_face = detect_regions(RegionParams(seed_face=seed_face, up_axis=tuple(bunny_regions.up)), bunny, touch_of(bunny))
    assert np.array_equal(by_face.base_faces, by_point.base_faces)
    narrow = detect_regions(RegionParams(angle_threshold_deg=8.0), bunny, touch_of(bunny))
    assert narrow.base_faces.sum() < bunny_regions.base_faces.sum()


def test_sphere_rests_on_a_contact_cap(sphere: Mesh) -> None:
    r = detect_regions(RegionParams(), sphere, touch_of(sphere))
    assert r.pose_kind == "round"
    cap = sphere.vertices[np.unique(sphere.faces[r.base_faces])]
    centre = sphere.vertices[r.base_centre]
    # a cap around the lowest point, wide enough that the centre is >= min_base_radius_mm inside
    assert np.linalg.norm(cap - centre, axis=1).max() < 25.0
    assert 0.005 < r.base_area_fraction < 0.05, r.base_area_fraction
    assert centre @ r.up < -49.0
    assert sphere.vertices[r.far_vertex] @ r.up > 49.0


def test_sphere_with_up_axis_gets_a_polar_cap(sphere: Mesh) -> None:
    r = detect_regions(RegionParams(up_axis="+z", exclusion_base_mm=5.0, exclusion_far_mm=8.0), sphere, touch_of(sphere))
    cap = sphere.vertices[np.unique(sphere.faces[r.base_faces])]
    # a polar cap grown until its rim (about 99 mm, 16 mm from the pole) has room for the wiring
    assert cap[:, 2].max() <= -50.0 + 4.0 and boundary_mm(sphere, r.base_faces) > 0.8 * RegionParams().wiring_room_mm
    assert "room for the wiring" in r.pose_reason
    assert sphere.vertices[r.base_centre][2] < -49.9
    assert sphere.vertices[r.far_vertex][2] > 49.0  # the north pole is farthest from the base


def test_bad_overrides() -> None:
    with pytest.raises(ValueError, match="up_axis"):
        RegionParams(up_axis="w")
    with pytest.raises(ValueError, match="not both"):
        RegionParams(seed_face=1, seed_point=(0.0, 0.0, 0.0))
    np.testing.assert_allclose(parse_axis("-y"), [0.0, -1.0, 0.0])
    np.testing.assert_allclose(parse_axis((0.0, 3.0, 4.0)), [0.0, 0.6, 0.8])


def test_seed_face_out_of_range(sphere: Mesh) -> None:
    with pytest.raises(UserError, match="seed_face 99999 does not exist"):
        detect_regions(RegionParams(seed_face=99999), sphere, touch_of(sphere))

SHARED = sorted(SHARED_MESHES.glob("*.ply")) if SHARED_MESHES.is_dir() else []
POSE_KINDS = {"flat", "foot_ring", "patches", "round", "thin"}


def assert_valid_regions(mesh: Mesh, r: SurfaceRegions) -> None:
    """Partition, dipole inside the base, base and sensing each one edge-connected piece, the base
    on the support plane, the recorded share right."""
    stacked = np.stack([r.base_faces, r.exclusion_base, r.exclusion_far, r.sensing_faces]).astype(int)
    assert (stacked.sum(axis=0) == 1).all()
    assert r.base_faces[vertex_faces(mesh, int(r.base_dipole[0]))].all()
    assert r.base_faces[vertex_faces(mesh, int(r.base_dipole[1]))].all()
    graph = FaceGraph(mesh.faces, len(mesh.vertices))
    assert graph.components(r.base_faces)[r.base_faces].max() == graph.components(r.base_faces)[r.base_faces].min()
    rest = graph.components(~r.base_faces)
    assert len(np.unique(rest[rest >= 0])) == 1  # the non-base surface is one piece
    height = mesh.vertices @ -r.up
    assert height[np.unique(mesh.faces[r.base_faces])].max() > height.max() - RegionParams().plane_tolerance_mm
    _, areas = normals(corners(mesh.vertices, mesh.faces))
    assert abs(r.base_area_fraction - areas[r.base_faces].sum() / areas.sum()) < 1e-9
    assert r.pose_kind in POSE_KINDS and r.pose_reason.startswith("rests on")
    assert len(r.base_boundary_edges) >= 6  # a closed loop around base and first exclusion
    assert abs(r.sensing_area_fraction - areas[r.sensing_faces].sum() / areas.sum()) < 1e-9
    reachable = graph.components(r.sensing_faces | r.exclusion_far)  # every sensing face reachable from the pole
    assert len(np.unique(reachable[reachable >= 0])) == 1


@pytest.mark.skipif(not SHARED, reason=f"no shared meshes in {SHARED_MESHES}")
@pytest.mark.parametrize("path", SHARED, ids=[p.stem for p in SHARED])
def test_shared_meshes_rest_without_overrides(path: Path) -> None:
    mesh = scale_mesh(ScaleParams(diagonal_mm=170.0), load_mesh(LoadParams(path=str(path))))
    params = RegionParams()
    r = detect_regions(params, mesh, touch_of(mesh))
    assert_valid_regions(mesh, r)
    assert r.tipping_angle_deg >= params.min_tipping_deg  # a stable pose
    # most of the surface senses; on a thin object its top (the bottom side and the rounded underside
    # beside it that no finger reaches above the table are the base: a sword's grip and guard)
    assert r.sensing_faces.mean() > (0.3 if r.pose_kind == "thin" else 0.45)
    if r.pose_kind == "thin":  # the Tx pole at the other end from the base centre (a lying blade's tip)
        span = np.linalg.norm(mesh.vertices[r.far_vertex] - mesh.vertices[r.base_centre])
        assert span > 0.5 * np.linalg.norm(np.ptp(mesh.vertices, axis=0)), span
    else:
        height = mesh.vertices @ r.up - (mesh.vertices @ r.up).min()
        span = np.linalg.norm(mesh.vertices[r.far_vertex] - mesh.vertices[r.base_centre])
        # not a second foot: high up, or (a lying spoon's handle end) the object's length away
        assert height[r.far_vertex] > 0.25 * height.max() or span > 0.5 * np.linalg.norm(np.ptp(mesh.vertices, axis=0))
        assert r.base_distance_mm[r.far_vertex] > 0.5 * height.max()  # far from the base (the hip, a leg's top)


def remeshed(tm: trimesh.Trimesh, vertices: int = 2000) -> Mesh:
    mesh = Mesh(np.asarray(tm.vertices), np.asarray(tm.faces, dtype=np.int64), "shape")
    return remesh(RemeshParams(target_vertices=vertices), mesh)


def test_bottle_stands_on_an_end_and_box_lies_on_its_largest_face() -> None:
    bottle = remeshed(trimesh.creation.cylinder(radius=30.0, height=200.0, sections=96))
    r = detect_regions(RegionParams(), bottle, touch_of(bottle))
    assert abs(r.up[2]) > 0.99 and r.pose_kind == "flat"
    box = remeshed(shapes.box())
    r = detect_regions(RegionParams(), box, touch_of(box))
    assert abs(r.up[2]) > 0.99 and r.pose_kind == "flat"  # the 120 x 80 face, not a side
    # the box lies (50 mm high, under half its 120 mm length): the base is that face and the band of the
    # sides beside the table that a 5 mm fingertip cannot reach
    band = 2 * (120 + 80) * r.touch["finger_radius_mm"]
    assert abs(r.base_area_fraction - (120 * 80 + band) / (2 * (120 * 80 + 120 * 50 + 80 * 50))) < 0.03


def test_bowl_rests_on_its_foot_ring_not_upside_down() -> None:
    bowl = remeshed(shapes.bowl_with_foot_ring())
    r = detect_regions(RegionParams(), bowl, touch_of(bowl))
    assert r.up[2] > 0.99 and r.pose_kind == "foot_ring"
    assert "1 upside-down pose(s) passed over" in r.pose_reason
    centre = bowl.vertices[r.base_centre]
    assert np.hypot(centre[0], centre[1]) < 10.0  # the Tx singularity inside the ring, near the axis
    assert_valid_regions(bowl, r)


def test_figurine_base_is_one_leg_and_the_rest_one_piece() -> None:
    """The base starts on one sole and grows up its leg (a neck 35-40 mm round) to the body, where
    the traces have room; the other three feet stay sensing."""
    figurine = remeshed(shapes.four_legged_figurine(), 3000)
    r = detect_regions(RegionParams(), figurine, touch_of(figurine))
    assert r.up[2] > 0.99 and r.pose_kind == "patches" and "of 4 contact patches" in r.pose_reason
    assert "room for the wiring" in r.pose_reason
    assert_valid_regions(figurine, r)
    base = figurine.vertices[np.unique(figurine.faces[r.base_faces])]
    assert base[:, 2].max() > -25.0  # up the leg, past its narrow part (the body's belly is at z = -20)
    soles = figurine.vertices[:, 2] < -44.0
    feet = np.unique(np.sign(figurine.vertices[soles, :2]), axis=0)
    assert len(feet) == 4 and len(np.unique(np.sign(base[base[:, 2] < -44.0, :2]), axis=0)) == 1  # one foot
    assert r.base_area_fraction < 0.2
    assert boundary_mm(figurine, r.base_faces) > 0.8 * RegionParams().wiring_room_mm


def wine_glass() -> Mesh:
    """A foot disc (35 mm radius), a stem 8 mm thick and 54 mm long, a bowl 80 mm wide on top."""
    profile = [(0.0, 0.0), (35.0, 0.0), (35.0, 3.0), (4.0, 6.0), (4.0, 60.0), (20.0, 65.0), (38.0, 85.0),
               (40.0, 105.0), (0.0, 108.0)]
    return remeshed(shapes.revolved(profile), 3000)


def test_base_grows_over_a_stem_to_the_bowl() -> None:
    """Every trace would squeeze through a stem 25 mm round: the base takes foot and stem, and its
    boundary, at the bowl, is long enough for the wiring; the bowl senses."""
    glass = wine_glass()
    r = detect_regions(RegionParams(), glass, touch_of(glass))
    assert_valid_regions(glass, r)
    height = glass.vertices[:, 2]
    assert height[np.unique(glass.faces[r.base_faces])].max() > 58.0
    assert r.base_area_fraction <= RegionParams().max_base_share
    bowl = (height[glass.faces] > 70.0).all(axis=1)
    assert r.sensing_faces[bowl].mean() > 0.9
    kept = detect_regions(RegionParams(wiring_room_mm=0.0), glass, touch_of(glass))  # growth off: the foot alone
    assert height[np.unique(glass.faces[kept.base_faces])].max() < 6.0 and "wiring" not in kept.pose_reason


def boundary_mm(mesh: Mesh, base: np.ndarray) -> float:
    """Length (mm) of the base's boundary, summed over edges between a base and a non-base face."""
    graph = FaceGraph(mesh.faces, len(mesh.vertices))
    a, b = graph.pairs[:, 0], graph.pairs[:, 1]
    edges = graph.halfedges[np.flatnonzero(graph.opposite >= 0)][base[a] & ~base[b]]
    return float(np.linalg.norm(mesh.vertices[edges[:, 0]] - mesh.vertices[edges[:, 1]], axis=1).sum())


def test_narrow_lying_blade_keeps_its_top_sensing() -> None:
    """A 150 x 9 x 2 mm blade lies on its broad side; its bottom side is narrower than the dipole's
    radius, yet the base stays on the bottom (it does not wrap the top), and the Tx pole is at the
    other end from the base centre, so the Tx lines run along the blade."""
    blade = remeshed(trimesh.creation.box(extents=(150.0, 9.0, 2.0)), 3000)
    r = detect_regions(RegionParams(), blade, touch_of(blade))
    assert abs(r.up[2]) > 0.99 and r.pose_kind == "thin"
    face_normals, areas = normals(corners(blade.vertices, blade.faces))
    top = face_normals @ r.up > 0.9
    assert areas[top & r.sensing_faces].sum() > 0.85 * areas[top].sum()
    assert np.linalg.norm(blade.vertices[r.far_vertex] - blade.vertices[r.base_centre]) > 100.0
    assert_valid_regions(blade, r)


def spoon_ends(spoon: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Vertex masks of a spoon's handle end and bowl end: the outer 30 % of its length each, the
    narrower one the handle's."""
    centre = spoon.vertices.mean(axis=0)
    axes = np.linalg.svd(spoon.vertices - centre)[2]
    along, across = (spoon.vertices - centre) @ axes[0], (spoon.vertices - centre) @ axes[1]
    ends = [along < np.quantile(along, 0.3), along > np.quantile(along, 0.7)]
    handle = int(np.argmin([np.ptp(across[end]) for end in ends]))
    return ends[handle], ends[1 - handle]


@pytest.mark.skipif(not (SHARED_MESHES / "spoon_pfc.ply").exists(), reason=f"no spoon_pfc.ply in {SHARED_MESHES}")
def test_lying_spoon_is_a_sheet_with_its_bottom_side_as_base() -> None:
    """The spoon is a sheet (its wall 1.5 mm thick) lying on its bowl's curved back: a thin object
    although its bowl makes it 20 mm tall. The base is its whole bottom side, the top senses, and the
    Tx pole sits at the handle's end."""
    spoon = scale_mesh(ScaleParams(diagonal_mm=170.0), load_mesh(LoadParams(path=str(SHARED_MESHES / "spoon_pfc.ply"))))
    r = detect_regions(RegionParams(), spoon, touch_of(spoon))
    assert "thin object" in r.pose_reason
    face_normals, areas = normals(corners(spoon.vertices, spoon.faces))
    down = face_normals @ -np.asarray(r.up) > np.cos(np.radians(45.0))
    up = face_normals @ np.asarray(r.up) > np.cos(np.radians(45.0))
    assert areas[down & r.base_faces].sum() > 0.9 * areas[down].sum()
    assert areas[up & r.sensing_faces].sum() > 0.8 * areas[up].sum()
    assert spoon_ends(spoon)[0][r.far_vertex]
    assert_valid_regions(spoon, r)


@pytest.mark.skipif(not (SHARED_MESHES / "spoon_pfc.ply").exists(), reason=f"no spoon_pfc.ply in {SHARED_MESHES}")
def test_a_base_behind_a_neck_moves_to_the_contact_where_the_wiring_has_room(monkeypatch) -> None:
    """With the sheet and lying rules off (the base a contact cap), the spoon touches the table at the
    handle's end (the larger contact) and under the bowl; from the handle's end every trace would
    squeeze along the handle (under 30 mm round), so the base starts under the bowl, and the Tx pole is
    at the handle's end."""
    monkeypatch.setattr(detect, "is_sheet", lambda *mesh: False)
    monkeypatch.setattr(detect, "is_lying", lambda *mesh: False)
    spoon = scale_mesh(ScaleParams(diagonal_mm=170.0), load_mesh(LoadParams(path=str(SHARED_MESHES / "spoon_pfc.ply"))))
    r = detect_regions(RegionParams(), spoon, touch_of(spoon))
    assert "contact patch 2 by size" in r.pose_reason
    handle, bowl = spoon_ends(spoon)
    assert bowl[r.base_centre] and handle[r.far_vertex]
    assert_valid_regions(spoon, r)


@pytest.mark.parametrize("name, kind", [("metal_spoon", "thin"), ("sword_oded", "thin"), ("lying_spoon", "round")])
def test_a_thin_or_lying_object_senses_only_where_a_finger_reaches(name: str, kind: str) -> None:
    """A thin or lying object's base takes the underside beside it that a fingertip cannot reach above
    the table (a spoon's rounded edge, a sword's grip and guard, a solid spoon's lower half: 5 %, 29 %
    and 35 % of what sensed before), so its whole sensing region can be touched."""
    if name in shapes.CLASSES:
        mesh = remeshed(shapes.CLASSES[name](), 4000)
    elif (SHARED_MESHES / f"{name}.ply").exists():
        mesh = scale_mesh(ScaleParams(diagonal_mm=170.0), load_mesh(LoadParams(path=str(SHARED_MESHES / f"{name}.ply"))))
    else:
        pytest.skip(f"no {name}.ply in {SHARED_MESHES}")
    r = detect_regions(RegionParams(), mesh, touch_of(mesh))
    assert r.pose_kind == kind
    _, areas = normals(corners(mesh.vertices, mesh.faces))
    assert areas[r.sensing_faces & ~r.touch_faces].sum() < 0.005 * areas[r.sensing_faces].sum()
    assert_valid_regions(mesh, r)


def dish(outer_radius: float, rim_radius: float, wall_mm: float) -> trimesh.Trimesh:
    """A round-bottomed shell of revolution: a sphere's cap (``outer_radius``, out to ``rim_radius``)
    with a wall ``wall_mm`` thick (mm)."""
    inner_radius = outer_radius - wall_mm
    outer = [(r, outer_radius - np.sqrt(outer_radius**2 - r * r)) for r in np.linspace(0.0, rim_radius, 25)]
    inner = [(r, outer_radius - np.sqrt(inner_radius**2 - r * r)) for r in np.linspace(rim_radius, 0.0, 25)]
    return shapes.revolved(outer + inner)


def arch(radius: float, wall_mm: float, length: float) -> trimesh.Trimesh:
    """A sheet bent into an arch: half a cylindrical shell along y, standing on its two edges (mm)."""
    turn = np.linspace(0.0, np.pi, 49)
    outer = np.column_stack([radius * np.cos(turn), radius * np.sin(turn)])
    inner = np.column_stack([(radius - wall_mm) * np.cos(turn), (radius - wall_mm) * np.sin(turn)])[::-1]
    section = np.vstack([outer, inner])  # closed outline in (x, z)
    k = len(section)
    ys = np.linspace(0.0, length, 51)
    vertices = np.vstack([np.column_stack([section[:, 0], np.full(k, y), section[:, 1]]) for y in ys])
    m = len(turn)
    caps = []
    for offset, flip in ((0, False), ((len(ys) - 1) * k, True)):  # the two end faces: strips between the arcs
        o, n = offset + np.arange(m - 1), offset + k - 1 - np.arange(m - 1)
        cap = np.vstack([np.column_stack([o, n, o + 1]), np.column_stack([o + 1, n, n - 1])])
        caps.append(cap[:, ::-1] if flip else cap)
    return shapes.swept(vertices, len(ys), k, np.vstack(caps))


def test_a_sheet_standing_on_its_edges_is_not_thin() -> None:
    """An arch of a 2 mm sheet set on its two edges rests on two strips, not on a side: its base is a
    contact cap grown for the dipole and the wiring, as a solid's (a thin object's base would be one
    edge strip)."""
    mesh = remeshed(arch(40.0, 2.0, 100.0), 4000)
    face_normals, areas = normals(corners(mesh.vertices, mesh.faces))
    assert is_sheet(mesh.vertices, mesh.faces, face_normals, areas)
    r = detect_regions(RegionParams(up_axis=(0.0, 0.0, 1.0)), mesh, touch_of(mesh))
    assert r.pose_kind != "thin"
    assert_valid_regions(mesh, r)


@pytest.mark.parametrize("wall_mm, kind", [(2.5, "thin"), (12.0, "round")])
def test_a_sheet_resting_on_a_curved_bottom_is_thin_a_solid_is_round(wall_mm: float, kind: str) -> None:
    """The same round-bottomed dish (94 mm across, 27-50 mm tall: too tall to be thin by its height) is a
    sheet with a 2.5 mm wall, whose whole bottom side is the base, and with a 12 mm wall a solid
    resting on a contact cap."""
    mesh = remeshed(dish(60.0, 47.0, wall_mm), 4000)
    face_normals, areas = normals(corners(mesh.vertices, mesh.faces))
    assert is_sheet(mesh.vertices, mesh.faces, face_normals, areas) == (kind == "thin")
    r = detect_regions(RegionParams(), mesh, touch_of(mesh))
    assert r.pose_kind == kind
    down = face_normals @ np.array([0.0, 0.0, -1.0]) > np.cos(np.radians(45.0))
    base_share_of_bottom = areas[down & r.base_faces].sum() / areas[down].sum()
    assert base_share_of_bottom > 0.9 if kind == "thin" else base_share_of_bottom < 0.5
    assert_valid_regions(mesh, r)


@pytest.mark.skipif(not (SHARED_MESHES / "scorpion_lowres_oded.ply").exists(),
                    reason=f"no scorpion_lowres_oded.ply in {SHARED_MESHES}")
def test_legs_cut_off_from_the_pole_are_not_sensing_and_the_note_says_so() -> None:
    """The scorpion stands on eight legs; its base and the exclusion around it cut some legs off from
    the body. No trace from the Tx pole reaches them, so they join the first exclusion, and the note
    gives their share of the surface."""
    path = SHARED_MESHES / "scorpion_lowres_oded.ply"
    scorpion = scale_mesh(ScaleParams(diagonal_mm=170.0), load_mesh(LoadParams(path=str(path))))
    r = detect_regions(RegionParams(), scorpion, touch_of(scorpion))
    assert_valid_regions(scorpion, r)
    _, areas = normals(corners(scorpion.vertices, scorpion.faces))
    within = r.base_distance_mm[scorpion.faces].mean(axis=1) < RegionParams().exclusion_base_mm
    beyond_radius = areas[r.exclusion_base & ~within].sum() / areas.sum()
    found = re.search(r"; ([0-9.]+)% of the surface is cut off from the Tx pole", r.pose_reason)
    assert found, r.pose_reason
    assert 0.02 < beyond_radius <= float(found[1]) / 100 + 5e-4 <= areas[r.exclusion_base].sum() / areas.sum() + 1e-3
