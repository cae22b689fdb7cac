"""The plain data passed between retrotouch nodes.

Conventions stated once for the whole project:

* Lengths in millimetres (after ingest), angles in radians (degrees only in YAML params).
* ``vertices`` (n, 3) float64; ``faces`` (m, 3) int64, counter-clockwise seen from outside, so
  ``cross(P1 - P0, P2 - P0)`` points outward.
* Barycentric coordinates ``bary[k] = (l0, l1, l2)`` refer to the corners ``faces[f]`` in order and
  sum to 1; a point is ``bary @ vertices[faces[f]]``.
* Curve sets are stored flat: curve ``c`` owns rows ``offsets[c]:offsets[c + 1]``. Segment ``k``
  (row ``k`` to row ``k + 1`` of the same curve) lies inside face ``faces[k]``; row ``k``'s
  barycentrics are with respect to ``faces[k]``. A curve's last row repeats the face of its last
  segment. Points where a curve crosses an edge are stored once, in the face the curve enters.
  Curves are oriented from their start (Tx: the far singularity; Rx: the base boundary) to their
  end.
"""
from __future__ import annotations

import dataclasses
from enum import IntEnum

import numpy as np


@dataclasses.dataclass(frozen=True)
class Mesh:
    """A closed triangle mesh in millimetres (see the module conventions)."""

    vertices: np.ndarray  # (n, 3) float64, mm
    faces: np.ndarray  # (m, 3) int64, CCW from outside
    source: str  # where it came from (file name or "builtin:bunny"), for reports only
    repairs: tuple[str, ...] = ()  # what ingest changed (reconstruction, fragments, holes, ...), one line each

    @property
    def source_name(self) -> str:
        """``source`` without the content hash that ``mesh.load`` appends (``" sha256:<hex>"``)."""
        return self.source.split(" sha256:")[0]


class CurveEnd(IntEnum):
    """Why tracing stopped, per curve."""

    BASE = 0  # reached the non-sensing base boundary (the wanted case)
    SINGULARITY = 1  # came within the stop radius of a singularity
    SINK_EDGE = 2  # both faces of an edge point at it
    LOOP = 3  # loop guard (revisited a face in the same direction)
    MAX_STEPS = 4  # step budget exhausted


@dataclasses.dataclass(frozen=True)
class CurveSet:
    """One layer's family of traced curves (module conventions: flat storage, per-segment faces)."""

    layer: str  # "tx" or "rx"
    points: np.ndarray  # (P, 3) float64, mm
    faces: np.ndarray  # (P,) int64
    bary: np.ndarray  # (P, 3) float64
    offsets: np.ndarray  # (C + 1,) int64
    lengths_mm: np.ndarray  # (C,) float64, polyline length in mm
    end_reason: np.ndarray  # (C,) int8, CurveEnd codes
    angle: float  # Rx initial angular offset (dipole), corridor position (rings), 0 / pi winding left / right (helices), in radians; 0.0 for Tx
    # "field" (Tx lines), "dipole" (Rx dipole loops), "rings" / "rings_tx" (Rx rings, legs side by side / on Tx lines),
    # "helices", "grid" / "grid_plan" (geodesic / plan coordinates); rings and helices on the per-line climb add "_per_line"
    family: str = "field"
    # Tx: (C,) int64, the field line each lane copies up to where it turns beside another line
    # (``curves.tx_lanes``), -1 for the field lines themselves; None when the family has no lanes
    lane_parent: np.ndarray | None = None
    # (C,) int64, the limb each curve of ``curves.trace_limbs`` serves (its rank among the base distance's dead
    # ends), -1 for the family's own curves; None when no limb curves were added
    limb: np.ndarray | None = None

    @property
    def count(self) -> int:
        return len(self.offsets) - 1

    def curve(self, c: int) -> slice:
        """Row slice of curve ``c``."""
        return slice(int(self.offsets[c]), int(self.offsets[c + 1]))


def _segments(points: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(curve of each row (P,), length (mm) from each row to the next (P - 1,), 0 from a curve's last
    row to the next curve's first) of polylines packed as ``points[offsets[c]:offsets[c + 1]]``."""
    row_curve = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return row_curve, np.where(row_curve[1:] == row_curve[:-1], seg, 0.0)


def row_arcs(curves: CurveSet) -> np.ndarray:
    """(P,) arc length (mm) of every row from its curve's first row."""
    row_curve, seg = _segments(curves.points, curves.offsets)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    return cum - cum[curves.offsets[:-1]][row_curve]


def curve_lengths(points: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(C,) length (mm) of each of the C polylines packed as ``points[offsets[c]:offsets[c + 1]]``."""
    row_curve, seg = _segments(points, offsets)
    return np.bincount(row_curve[:-1], weights=seg, minlength=len(offsets) - 1)


@dataclasses.dataclass(frozen=True)
class Crossings:
    """Crossings between curves of layer ``layer_a`` and layer ``layer_b`` (possibly the same layer).

    Row ``k`` is one crossing of curve ``curve_a[k]`` with curve ``curve_b[k]`` at ``points[k]``
    inside face ``faces[k]`` (barycentrics ``bary[k]``); ``arc_a``/``arc_b`` are the arc lengths (mm)
    from each curve's start to the crossing, ``seg_a``/``seg_b`` the segment indices (row offsets
    within the curve). For a same-layer set each unordered pair appears once with ``curve_a < curve_b``.
    """

    layer_a: str
    layer_b: str
    curve_a: np.ndarray  # (K,) int64
    curve_b: np.ndarray  # (K,) int64
    seg_a: np.ndarray  # (K,) int64
    seg_b: np.ndarray  # (K,) int64
    arc_a: np.ndarray  # (K,) float64, mm
    arc_b: np.ndarray  # (K,) float64, mm
    points: np.ndarray  # (K, 3) float64, mm
    faces: np.ndarray  # (K,) int64
    bary: np.ndarray  # (K, 3) float64


PAD_RADIUS_MM = 2.0  # electrode pad radius before any relaxation
TRACE_WIDTH_MM = 1.0  # conductive trace width
CLEARANCE_MM = 1.0  # edge-to-edge gap between two traces of one layer


@dataclasses.dataclass(frozen=True)
class Layout:
    """The optimised sensor layout on one mesh, with the design values it was made for.

    ``tx``/``rx`` hold only the selected curves, in channel order (Tx00 is ``tx`` curve 0).
    ``cells`` are their Tx x Rx crossings with ``curve_a`` = Tx channel and ``curve_b`` = Rx channel,
    at most one row per channel pair; ``pad[k]`` says whether an electrode pad is placed at row k.
    ``tx_source``/``rx_source`` map channels back to curve ids in the candidate families.
    ``pad_radius_mm`` and ``d_min_mm`` are the pad radius and geodesic pad spacing actually used
    (after any relaxation); two traces of one layer keep ``trace_width_mm + clearance_mm`` between
    their centre lines. Outlines, textures, projection and the sensing map read them from here.
    """

    tx: CurveSet
    rx: CurveSet
    cells: Crossings
    pad: np.ndarray  # (K,) bool
    tx_source: np.ndarray  # (Ntx,) int64
    rx_source: np.ndarray  # (Nrx,) int64
    pad_radius_mm: float = PAD_RADIUS_MM
    d_min_mm: float = 4.0 * PAD_RADIUS_MM
    trace_width_mm: float = TRACE_WIDTH_MM
    clearance_mm: float = CLEARANCE_MM

    def design_values(self) -> dict[str, float]:
        """The design values above by name (mm), as output files record them."""
        return {"pad_radius_mm": self.pad_radius_mm, "d_min_mm": self.d_min_mm,
                "trace_width_mm": self.trace_width_mm, "clearance_mm": self.clearance_mm}


@dataclasses.dataclass(frozen=True)
class SurfaceRegions:
    """Base (non-sensing), exclusion and sensing regions of a mesh, and the singularity anchors.

    The face masks ``base_faces``, ``exclusion_base``, ``exclusion_far`` and ``sensing_faces`` are
    disjoint and cover every face; ``touch_faces`` is the part of ``sensing_faces`` a finger can touch.
    ``base_boundary_edges`` are the halfedges ``(a, b)`` of sensing faces whose neighbour across the
    edge is base or first exclusion: CCW in the sensing face, so the sensing region lies to the left
    of ``a -> b``. Distances are geodesic (heat method), mm.
    """

    base_faces: np.ndarray  # (m,) bool, the region the object rests on
    exclusion_base: np.ndarray  # (m,) bool, first exclusion ring grown from the base
    exclusion_far: np.ndarray  # (m,) bool, geodesic disc around far_vertex and the untouchable pocket around it
    sensing_faces: np.ndarray  # (m,) bool, where curves may run
    touch_faces: np.ndarray  # (m,) bool, the sensing faces a finger can touch: where coverage counts
    base_centre: int  # interior base vertex farthest from the base boundary (Tx singularity)
    base_dipole: np.ndarray  # (2,) int64, base_centre and an adjacent interior base vertex (Rx)
    far_vertex: int  # vertex farthest from the base outside base/exclusion_base (Tx singularity)
    up: np.ndarray  # (3,) float64 unit vector, opposite to the resting direction
    base_boundary_edges: np.ndarray  # (E, 2) int64 vertex pairs, see above
    base_distance_mm: np.ndarray  # (n,) float64, geodesic distance of each vertex from the base
    far_distance_mm: np.ndarray  # (n,) float64, from far_vertex (where Tx lines start)
    centre_distance_mm: np.ndarray  # (n,) float64, from base_centre (where Tx lines end and Rx lines start)
    dipole_distance_mm: np.ndarray  # (n,) float64, from the nearer of the base_dipole vertices (where Rx lines end)
    pose_kind: str  # what the object rests on: flat, foot_ring, patches, round or thin
    pose_reason: str  # one sentence: the base, its share of the surface, the stability, why
    tipping_angle_deg: float  # smallest tilt (deg) that topples the object in this pose
    base_area_fraction: float  # base area / surface area
    sensing_area_fraction: float  # sensing area / surface area
    tx_pole: str  # how far_vertex was chosen: "far", "top" or "centre" (regions.detect's tx_pole)
    touch: dict  # the finger model and the touchable share of the surface (metrics.json's "touch")


@dataclasses.dataclass(frozen=True)
class TouchField:
    """Where a finger can touch (``regions.touchable``): the distance (mm) from the grid point
    ``origin + pitch_mm * (i, j, k)`` to the nearest position the fingertip ball's centre can reach,
    and the finger model that decided it. A surface point is touchable where the distance is about
    ``finger_radius_mm``."""

    origin: np.ndarray  # (3,) float64, mm
    pitch_mm: float
    distance_mm: np.ndarray  # (nx, ny, nz) float32
    finger_radius_mm: float
    hand_radius_mm: float
    finger_reach_mm: float
