"""geometry.dead_ends: the merge tree of a function's superlevel sets on a closed mesh, checked on
bumps of known heights over a sphere (the floor between them is 0, so each lower bump is a dead end
as deep as its height)."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from retrotouch.nodes.geometry.dead_ends import dead_end_vertices, dead_ends, mesh_edges

SPHERE = trimesh.creation.icosphere(subdivisions=5)


def bumps(centres, heights, width: float = 0.3) -> np.ndarray:
    """Vertex values: a Gaussian bump of each height (mm) around each unit direction (width in radians)."""
    v = SPHERE.vertices
    values = np.zeros(len(v))
    for centre, height in zip(centres, heights):
        c = np.asarray(centre, dtype=np.float64) / np.linalg.norm(centre)
        values = np.maximum(values, height * np.exp(-((np.arccos(np.clip(v @ c, -1, 1)) / width) ** 2)))
    return values


def angle_to(centre) -> np.ndarray:
    c = np.asarray(centre, dtype=np.float64) / np.linalg.norm(centre)
    return np.arccos(np.clip(SPHERE.vertices @ c, -1, 1))


def test_each_lower_bump_is_a_dead_end_as_deep_as_its_height():
    centres, heights = [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0)], [40.0, 30.0, 20.0, 12.0]
    values, edges = bumps(centres, heights), mesh_edges(SPHERE.faces)
    ends = dead_ends(values, edges, 5.0)
    assert [e.depth for e in ends] == pytest.approx([30.0, 20.0, 12.0], abs=0.5)  # deepest first; the highest never ends
    for end, centre in zip(ends, centres[1:]):
        assert angle_to(centre)[end.tip] < 0.05
        assert end.join_value == pytest.approx(0.0, abs=0.1)  # where two bumps' tails meet, 45 deg from each
        assert end.depth == pytest.approx(values[end.tip] - end.join_value)
    masks = [dead_end_vertices(values, edges, end) for end in ends]
    for mask, end, centre in zip(masks, ends, centres[1:]):
        assert mask[end.tip] and (angle_to(centre)[mask] < np.pi / 3).all()  # its own bump only (the others: 90 deg away)
    assert not (masks[0] & masks[1]).any() and not (masks[1] & masks[2]).any()
    assert [e.depth for e in dead_ends(values, edges, 15.0)] == pytest.approx([30.0, 20.0], abs=0.5)
    assert dead_ends(bumps(centres[:1], heights[:1]), edges, 1.0) == []  # one maximum: no dead end


def test_a_dead_end_holds_the_shallower_ones_that_joined_it():
    """A small bump on the flank of a middle one joins it before the middle one joins the highest."""
    values = np.maximum(bumps([(1, 0, 0), (-1, 0, 0)], [50.0, 30.0], width=0.5),
                        bumps([(-1, 0.35, 0)], [26.0], width=0.12))
    edges = mesh_edges(SPHERE.faces)
    middle, small = dead_ends(values, edges, 1.0)
    assert middle.depth == pytest.approx(30.0, abs=0.5) and 0.0 < small.depth < 26.0
    assert angle_to((-1, 0.35, 0))[small.tip] < 0.05 and small.join_value > middle.join_value
    inner, outer = dead_end_vertices(values, edges, small), dead_end_vertices(values, edges, middle)
    assert inner[small.tip] and not (inner & ~outer).any() and outer.sum() > inner.sum()


def test_the_metrics_limbs_are_the_dead_ends_that_sense_with_their_sensing_area_and_cells():
    from retrotouch.nodes.geometry.triangles import areas, corners
    from retrotouch.nodes.layout.metrics import limbs

    centres, heights = [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0)], [40.0, 30.0, 20.0, 12.0]
    values, faces, edges = bumps(centres, heights), SPHERE.faces, mesh_edges(SPHERE.faces)
    vertices = SPHERE.vertices * 50.0
    on = [dead_end_vertices(values, edges, end)[faces].all(axis=1) for end in dead_ends(values, edges, 10.0)]
    sensing = ~on[1]  # the 20 mm bump is a foot inside the base
    cell_faces = np.flatnonzero(angle_to((-1, 0, 0))[faces].max(axis=1) < 0.1)[:3]  # three cells on the 30 mm bump
    found = limbs(vertices, faces, values, sensing, cell_faces)
    assert [limb["depth_mm"] for limb in found] == pytest.approx([30.0, 12.0], abs=0.5)
    assert [limb["cells"] for limb in found] == [3, 0]
    assert found[0]["area_mm2"] == pytest.approx(areas(corners(vertices, faces))[on[0] & sensing].sum())
