"""regions.touchable: what a finger (a 5 mm ball, 70 mm beyond where a 25 mm hand ball fits) can touch,
on revolved shapes whose answer is known: grooves narrower and wider than the fingertip, deep tubes
narrower and wider than the hand, a ball resting on the table; the vase's inside joining the far
exclusion (and a pocket reaching the base not joining it), and the samples the layout draws."""
from __future__ import annotations

import types

import numpy as np
import pytest
import trimesh
from shapes import vase

from retrotouch.graph.errors import UserError
from retrotouch.nodes.data.types import Mesh
from retrotouch.nodes.geometry.triangles import areas, corners, normals
from retrotouch.nodes.layout.samples import SamplesParams, sample_surface, surface_samples
from retrotouch.nodes.mesh.repair import RemeshParams, remesh
from retrotouch.nodes.regions import touch
from retrotouch.nodes.regions.detect import RegionParams, detect_regions
from retrotouch.nodes.regions.faces import FaceGraph
from retrotouch.nodes.regions.touch import (TouchParams, clear_of_table, pocket_of, touch_field, touchable_faces_of,
                                            touchable_surface)

FINGER, HAND, REACH = 5.0, 25.0, 70.0


def revolved(profile, max_edge_mm: float = 2.0) -> Mesh:
    """A closed mesh revolving ``profile`` ((r, z) mm, from the axis back to it) about z."""
    m = trimesh.creation.revolve(np.asarray(profile, dtype=float), sections=96)
    v, f = trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge_mm)
    mesh = trimesh.Trimesh(v, f)
    assert mesh.is_watertight and mesh.volume > 0
    return Mesh(vertices=np.asarray(mesh.vertices, dtype=float), faces=np.asarray(mesh.faces, dtype=np.int64), source="test")


def grooved_cylinder(width: float, depth: float) -> Mesh:
    """A cylinder (radius 40, height 80 mm) with a ring groove of ``width`` x ``depth`` around its middle."""
    low, high = 40 - width / 2, 40 + width / 2
    return revolved([[0, 0], [40, 0], [40, low], [40 - depth, low], [40 - depth, high], [40, high], [40, 80], [0, 80]])


def tube(inner_radius: float, depth: float = 150.0, wall: float = 3.0) -> Mesh:
    """A closed-bottom tube (a test tube or a mug): ``inner_radius`` mm inside, ``depth`` mm deep, opening up."""
    outer = inner_radius + wall
    return revolved([[0, 0], [outer, 0], [outer, depth + wall], [inner_radius, depth + wall], [inner_radius, wall], [0, wall]],
                    max_edge_mm=3.0)


def face_mask(mesh: Mesh) -> np.ndarray:
    return touchable_faces_of(touchable_surface(TouchParams(), mesh), mesh.vertices, mesh.faces)


def sphere(radius: float) -> Mesh:
    tm = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    return Mesh(vertices=np.asarray(tm.vertices), faces=np.asarray(tm.faces, dtype=np.int64), source="sphere")


def test_the_defaults_are_an_adult_fingertip_and_hand():
    assert (TouchParams().finger_radius_mm, TouchParams().hand_radius_mm, TouchParams().finger_reach_mm) == (FINGER, HAND, REACH)


def test_a_convex_object_is_touchable_everywhere():
    ball = sphere(40.0)
    field = touchable_surface(TouchParams(), ball)
    assert touchable_faces_of(field, ball.vertices, ball.faces).all() and field.pitch_mm == FINGER / 4


@pytest.mark.parametrize("width, floor_touchable", [(6.0, False), (14.0, True)])
def test_a_groove_floor_is_touchable_only_when_the_fingertip_fits(width, floor_touchable):
    mesh = grooved_cylinder(width, depth=15.0)
    mask = face_mask(mesh)
    c = corners(mesh.vertices, mesh.faces).mean(axis=1)
    radius = np.hypot(c[:, 0], c[:, 1])
    floor = (np.abs(radius - 25.0) < 0.5) & (np.abs(c[:, 2] - 40.0) < width / 2)
    outer = radius > 39.9
    assert floor.sum() > 100 and mask[outer].all()
    if floor_touchable:  # where the ball rests on the floor, clear of the walls' corners
        assert mask[floor & (np.abs(c[:, 2] - 40.0) < width / 2 - FINGER)].all()
    else:
        assert not mask[floor].any()


def test_a_finger_reaches_down_a_narrow_tube_as_far_as_it_is_long():
    mesh = tube(inner_radius=8.0)  # the 5 mm fingertip goes in, the 25 mm hand does not
    mask = face_mask(mesh)
    c = corners(mesh.vertices, mesh.faces).mean(axis=1)
    inner_wall = np.abs(np.hypot(c[:, 0], c[:, 1]) - 8.0) < 0.3
    depth = 153.0 - c[:, 2]  # below the rim
    assert mask[inner_wall & (depth < REACH - 15)].all()
    assert not mask[inner_wall & (depth > REACH + FINGER + 15)].any()
    assert mask[np.hypot(c[:, 0], c[:, 1]) > 10.9].all()  # the outside


def test_the_hand_goes_into_a_mug_so_all_of_it_is_touchable():
    assert face_mask(tube(inner_radius=35.0, depth=100.0)).all()


def test_a_large_object_coarsens_the_grid_to_the_voxel_budget():
    ball = sphere(600.0)
    field = touch_field(ball.vertices, ball.faces, TouchParams())
    pitch = field.pitch_mm
    assert pitch > FINGER / 4
    assert ((1200 + 2 * (HAND + 2 * pitch)) / pitch + 1) ** 3 <= touch.MAX_VOXELS * 1.01
    assert touchable_faces_of(field, ball.vertices, ball.faces).all()


def test_a_finer_remesh_of_the_same_surface_reads_the_same_field():
    coarse = tube(inner_radius=8.0)
    v, f = trimesh.remesh.subdivide_to_size(coarse.vertices, coarse.faces, 1.5)
    fine = Mesh(vertices=np.asarray(v), faces=np.asarray(f, dtype=np.int64), source="finer")
    field = touchable_surface(TouchParams(), coarse)
    a, b = touchable_faces_of(field, coarse.vertices, coarse.faces), touchable_faces_of(field, fine.vertices, fine.faces)
    share = [areas(corners(m.vertices, m.faces))[k].sum() / areas(corners(m.vertices, m.faces)).sum() for m, k in ((coarse, a), (fine, b))]
    assert share[0] == pytest.approx(share[1], abs=0.01)


def test_a_vase_inside_beyond_reach_joins_the_far_exclusion():
    tm = vase()
    mesh = remesh(RemeshParams(target_vertices=6000), Mesh(np.asarray(tm.vertices), np.asarray(tm.faces, dtype=np.int64), "vase"))
    regions = detect_regions(RegionParams(), mesh, touchable_surface(TouchParams(), mesh))
    c = corners(mesh.vertices, mesh.faces).mean(axis=1)
    radius = np.hypot(c[:, 0], c[:, 1])
    inner_wall = np.interp(c[:, 2], [3, 40, 100], [37, 47, 45])  # the profile's inside, 3 mm within the outside
    deep_inside = (c[:, 2] > 10) & (c[:, 2] < 90) & (radius < inner_wall + 1)  # 90+ mm below the lip
    assert regions.pose_kind == "flat" and regions.up[2] > 0.99
    assert deep_inside.sum() > 100 and regions.exclusion_far[deep_inside].all()
    assert not regions.sensing_faces[deep_inside].any()
    outer = (radius > inner_wall + 2) & (c[:, 2] > 10) & (c[:, 2] < 95)
    assert regions.sensing_faces[outer].all() and regions.touch_faces[outer].all()
    assert regions.touch["share"] < 0.7 and not (regions.touch_faces & ~regions.sensing_faces).any()


def test_the_samples_stay_on_what_can_be_touched():
    mesh = tube(inner_radius=8.0)
    touchable = face_mask(mesh)
    face_area = areas(corners(mesh.vertices, mesh.faces))
    assert 0.5 < face_area[touchable].sum() / face_area.sum() < 0.95
    sensing = corners(mesh.vertices, mesh.faces).mean(axis=1)[:, 2] > 10.0  # all but the bottom
    regions = types.SimpleNamespace(sensing_faces=sensing, touch_faces=sensing & touchable)
    samples = surface_samples(SamplesParams(count=60), mesh, regions)
    assert touchable[samples.faces].all() and sensing[samples.faces].all()
    assert samples.touch_area_mm2 == pytest.approx(face_area[sensing & touchable].sum())
    assert samples.sensing_area_mm2 == pytest.approx(face_area[sensing].sum())
    with pytest.raises(UserError, match="can touch none of the sensing region"):
        surface_samples(SamplesParams(count=60), mesh, types.SimpleNamespace(sensing_faces=sensing, touch_faces=np.zeros_like(sensing)))


def test_a_few_untouchable_faces_leave_the_other_samples_where_they_were():
    ball = sphere(60.0)
    sensing = np.ones(len(ball.faces), dtype=bool)
    untouchable = np.zeros_like(sensing)
    untouchable[:: len(ball.faces) // 50] = True  # about 1 % of the faces
    before = sample_surface(ball.vertices, ball.faces, sensing, sensing, 200, 0, 0.7)
    after = sample_surface(ball.vertices, ball.faces, sensing, sensing & ~untouchable, 200, 0, 0.7)
    assert not untouchable[after[0]].any()
    kept = {tuple(p) for p in before[2]}
    assert sum(tuple(p) in kept for p in after[2]) >= 0.8 * 200


def test_a_hand_smaller_than_the_finger_is_refused():
    with pytest.raises(ValueError, match="hand_radius_mm"):
        TouchParams(finger_radius_mm=10.0, hand_radius_mm=8.0)


def test_a_fingertip_on_the_table_meets_a_resting_ball_where_the_geometry_says():
    radius = 40.0
    ball = sphere(radius)
    face_normals = normals(corners(ball.vertices, ball.faces))[0]
    clear = clear_of_table(ball.vertices, ball.faces, face_normals, np.array([0.0, 0.0, -1.0]), FINGER)
    c = corners(ball.vertices, ball.faces).mean(axis=1)
    from_bottom = np.degrees(np.arccos(np.clip(-c[:, 2] / np.linalg.norm(c, axis=1), -1, 1)))
    contact = np.degrees(np.arccos((radius - FINGER) / (radius + FINGER)))  # 38.9 deg
    assert not clear[from_bottom < contact - 2].any() and clear[from_bottom > contact + 2].all()


def test_the_default_regions_leave_the_wedge_at_the_table_out_of_the_touchable_faces():
    radius = 40.0
    mesh = remesh(RemeshParams(target_vertices=3000), sphere(radius))
    regions = detect_regions(RegionParams(), mesh, touchable_surface(TouchParams(), mesh))
    height = corners(mesh.vertices, mesh.faces).mean(axis=1) @ regions.up - (mesh.vertices @ regions.up).min()
    meets = radius * (1 - (radius - FINGER) / (radius + FINGER))  # 8.9 mm: where a fingertip on the table meets it
    wedge = regions.sensing_faces & (height < meets - 1.0)
    assert wedge.any() and not regions.touch_faces[wedge].any()
    assert regions.touch_faces[regions.sensing_faces & (height > meets + 1.5)].all()


def test_an_untouchable_pocket_joins_the_far_exclusion_only_if_it_leaves_the_way_to_the_base_open():
    ball = sphere(40.0)
    c = corners(ball.vertices, ball.faces).mean(axis=1)
    graph = FaceGraph(ball.faces, len(ball.vertices))
    pole, base = c[:, 2] > 36.0, c[:, 2] < -36.0
    strip = (np.abs(c[:, 0]) < 6.0) & ~pole & ~base  # a meridian from the pole's exclusion down to the base
    assert not pocket_of(graph, pole, strip, base).any()
    upper = strip & (c[:, 2] > 0.0)
    assert np.array_equal(pocket_of(graph, pole, upper, base), upper)
