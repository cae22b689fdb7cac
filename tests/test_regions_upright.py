"""The automatic resting pose is the one a person would choose: on every generated class and on
each shared mesh with an obvious upright (decided by looking at renders of the file, one line of
reason each), the chosen up direction is within ``TOLERANCE_DEG`` of an expected one. Poses are
found on the file's mesh scaled to a 170 mm diagonal (generated shapes at their own size), without
remeshing: the pose is a property of the hull."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull

import shapes
from retrotouch.nodes.geometry.triangles import corners, normals
from retrotouch.nodes.regions import pose
from retrotouch.nodes.regions.base import is_sheet
from retrotouch.nodes.regions.detect import RegionParams, resting_base
from retrotouch.nodes.regions.pose import candidate_floors
from retrotouch.nodes.regions.faces import FaceGraph

SHARED_MESHES = Path(__file__).resolve().parents[1].parent / "shared" / "meshes"
TOLERANCE_DEG = 20.0
DIAGONAL_MM = 170.0

X, Y, Z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
NEG_X, NEG_Z = (-1.0, 0.0, 0.0), (0.0, 0.0, -1.0)

SHARED_UPRIGHT: dict[str, tuple[tuple[tuple[float, float, float], ...], str]] = {
    "airplane_oded": ((Z,), "landing gear below the fuselage at -z"),
    "blub_fish": ((Y,), "belly down, dorsal fin at +y"),
    "boat_oded": ((Y,), "keel down, deck open toward +y (a V hull may lean on its chine)"),
    "cat_lowres_oded": ((Y,), "paws at -y, tail up"),
    "duck_gao": ((Z,), "flat-ish bottom at -z, head at +z"),
    "goathead_oded": (((-0.34, 0.94, 0.0),), "sits on its neck cut, which faces -y tilted 20 deg toward +x"),
    "human_man_oded": ((Y,), "standing on the feet at -y"),
    "pear_gao": ((Y,), "stem at +y"),
    "penguin_oded": ((Y,), "feet at -y"),
    "scorpion_lowres_oded": ((Y,), "eight legs at -y, tail curled up"),
    "spoon_pfc": ((Z, NEG_Z), "lies flat: thinnest extent along z"),
    "spot_crane": ((Y,), "a cow: four legs at -y"),
    "sword_oded": ((X, NEG_X), "lies flat: blade faces normal to x"),
    "teddy1_gao": ((Y,), "sits on its bottom, ears at +y"),
}
"""Shared mesh stem -> (acceptable up directions, reason). Left out: hand_closed_oded (a hand with
a capped wrist may stand on the cap or lie on its palm or back)."""

KNOWN_WRONG = {
    "blub_fish": "belly down it tips at 4 deg with 37 mm^2 of contact and it has no mirror plane (bent tail, "
    "posed fins); it is set rolled 34 deg onto a pectoral fin",
}
"""Shared meshes whose chosen pose a person would still disagree with (strict xfail: a fix shows)."""

GENERATED_UPRIGHT = {
    "plate": (Z,),
    "bowl_foot_ring": (Z,),
    "four_legged_figurine": (Z,),
    "standing_figure": (Z,),
    "lying_spoon": (Z, NEG_Z),
    "metal_spoon": (Z, NEG_Z),
    "bust_cut_base": (Z,),
    "box": (Z, NEG_Z),
    "phone": (Z, NEG_Z),
}
"""Generated class -> acceptable up directions (the builders model +z up; the spoons, the box and the
phone lie on either broad side). The point-cloud scan is the bust's surface: its pose is the bust's, checked
end to end in ``test_corpus_classes.py``."""


def chosen_up(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The up direction ``regions.detect`` picks with no overrides."""
    graph = FaceGraph(faces, len(vertices))
    face_normals, areas = normals(corners(vertices, faces))
    down = resting_base(vertices, graph, face_normals, areas, RegionParams(), is_sheet(vertices, faces, face_normals, areas))[1]
    return -down


def angle_to_nearest_deg(up: np.ndarray, expected: tuple[tuple[float, float, float], ...]) -> float:
    """Angle (deg) between ``up`` and the nearest expected direction."""
    directions = np.asarray(expected, dtype=np.float64)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return float(np.degrees(np.arccos(np.clip((directions @ up).max(), -1.0, 1.0))))


@pytest.mark.parametrize("name", sorted(GENERATED_UPRIGHT))
def test_generated_class_rests_upright(name: str) -> None:
    mesh = shapes.CLASSES[name]()
    up = chosen_up(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64))
    assert angle_to_nearest_deg(up, GENERATED_UPRIGHT[name]) <= TOLERANCE_DEG, f"{name}: up {np.round(up, 2)}"


def test_rounded_hooves_stand_on_their_feet() -> None:
    """Four legs ending in rounded hooves touch the table with almost no flat area; the figurine
    still stands on them (the feet's polygon is its support), not on its back."""
    mesh = shapes.four_legged_figurine(soles=False)
    up = chosen_up(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64))
    assert angle_to_nearest_deg(up, (Z,)) <= TOLERANCE_DEG, f"up {np.round(up, 2)}"


def shared_cases() -> list:
    return [
        pytest.param(stem, marks=pytest.mark.xfail(reason=KNOWN_WRONG[stem], strict=True))
        if stem in KNOWN_WRONG else stem
        for stem in sorted(SHARED_UPRIGHT)
    ]


def shared_mesh(stem: str, diagonal_mm: float = DIAGONAL_MM) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices, faces)`` of a shared mesh centred and scaled to ``diagonal_mm`` (skips when absent)."""
    path = SHARED_MESHES / f"{stem}.ply"
    if not path.exists():
        pytest.skip(f"no shared mesh {path}")
    mesh = trimesh.load(str(path), process=False)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    vertices = (vertices - (vertices.min(axis=0) + vertices.max(axis=0)) / 2.0) * (
        diagonal_mm / np.linalg.norm(np.ptp(vertices, axis=0))
    )
    return vertices, np.asarray(mesh.faces, dtype=np.int64)


@pytest.mark.parametrize("stem", shared_cases())
def test_shared_mesh_rests_upright(stem: str) -> None:
    up = chosen_up(*shared_mesh(stem))
    expected, reason = SHARED_UPRIGHT[stem]
    assert angle_to_nearest_deg(up, expected) <= TOLERANCE_DEG, f"{stem} ({reason}): up {np.round(up, 2)}"


def test_two_feet_count_on_a_figure_standing_tall_only() -> None:
    """A figure on two small soles stands on them: its upright floor's contact is the polygon the
    soles span, larger than the strip it lies on; without the two-feet rule its soles alone are
    smaller than that strip. A sole split in two by a groove is still one foot. The lying spoon's two
    ends are no feet: it is not tall."""
    figure = shapes.standing_figure()
    vertices, faces = np.asarray(figure.vertices, dtype=np.float64), np.asarray(figure.faces, dtype=np.int64)
    params = RegionParams()

    def floors() -> list:
        return candidate_floors(vertices, faces, params.direction_cells, params.angle_threshold_deg, params.plane_tolerance_mm)

    def upright_and_lying(found: list) -> tuple:
        upright = max(found, key=lambda floor: -floor.down[2])
        return upright, max(floor.contact_mm2 for floor in found if floor is not upright and floor.tipping_deg > 0)

    upright, lying = upright_and_lying(floors())
    soles = vertices[vertices[:, 2] <= vertices[:, 2].min() + params.plane_tolerance_mm]
    assert upright.feet == 2
    assert upright.contact_mm2 >= 0.95 * ConvexHull(soles[:, :2]).volume
    assert upright.contact_mm2 > lying
    assert angle_to_nearest_deg(chosen_up(vertices, faces), (Z,)) <= TOLERANCE_DEG
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(pose, "STRIDE_SHARE", 10.0)  # feet never apart that high: the rule off
        upright, lying = upright_and_lying(floors())
        assert upright.feet == 0 and upright.contact_mm2 < lying

    lowest = vertices[:, 2].min()  # a groove across one sole splits it into heel and toe: still one foot
    grooved = vertices.copy()
    grooved[(vertices[:, 0] > 0) & (np.abs(vertices[:, 1]) < 1.5) & (vertices[:, 2] < lowest + 0.5), 2] += 3.0
    found = candidate_floors(grooved, faces, params.direction_cells, params.angle_threshold_deg, params.plane_tolerance_mm)
    assert max(found, key=lambda floor: -floor.down[2]).feet == 2

    spoon = shapes.lying_spoon()
    found = candidate_floors(np.asarray(spoon.vertices, dtype=np.float64), np.asarray(spoon.faces, dtype=np.int64),
                             params.direction_cells, params.angle_threshold_deg, params.plane_tolerance_mm)
    assert all(floor.feet == 0 for floor in found)


@pytest.mark.parametrize("diagonal_mm", [80.0, 400.0])
def test_the_pose_is_the_shapes_not_its_sizes(diagonal_mm: float) -> None:
    """The same shape at another size rests the same way (the goat head turned over at 80 mm when the
    contact tolerances were judged at the object's own size)."""
    for stem in ("goathead_oded", "human_man_oded", "spot_crane", "teddy1_gao"):
        reference = chosen_up(*shared_mesh(stem))
        assert angle_to_nearest_deg(chosen_up(*shared_mesh(stem, diagonal_mm)), (tuple(reference),)) <= 1.0, stem
