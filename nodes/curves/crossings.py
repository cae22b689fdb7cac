"""``curves.crossings``: where traced curves cross (Tx x Rx, Tx x Tx, Rx x Rx).

Two curves can only cross inside a face both pass through, so segments are bucketed by face and
every pair of segments sharing a face is intersected in that face's affine coordinates
``(l1, l2)`` (barycentrics without ``l0``). Affine maps keep ratios along a segment, so the
parameters ``s``, ``t`` of the 2D intersection are the true fractions along both 3D segments; the
crossing's barycentrics, 3D point and arc lengths follow by interpolation. Parameters are
half-open (``0 <= s < 1``) so a crossing exactly on an edge is counted once.

Same-layer crossings (each unordered pair once, ``curve_a < curve_b``) within
``singularity_exclusion_mm`` (geodesic) of one of the layer's singularities are dropped: curves of
one family all meet there by construction. Tx x Rx crossings are all kept;
:func:`pair_multiplicity` counts them per curve pair (the layout needs pairs crossing exactly once).
"""
from __future__ import annotations

import dataclasses

import numpy as np
from pydantic import Field

from ...graph.node import NodeParams, node
from .connection import DirectionField
from ..data.types import Crossings, CurveSet, Mesh


@dataclasses.dataclass(frozen=True)
class Segments:
    """The segments of a curve set: row ``k`` of the set to row ``k + 1``, inside ``face``."""

    curve: np.ndarray  # (S,) int64
    row: np.ndarray  # (S,) int64, row index of the segment start in the CurveSet
    index: np.ndarray  # (S,) int64, segment index within its curve (row offset from the curve start)
    face: np.ndarray  # (S,) int64
    start_bary: np.ndarray  # (S, 3) with respect to face
    end_bary: np.ndarray  # (S, 3) with respect to face
    start_arc: np.ndarray  # (S,) mm from the curve start
    length: np.ndarray  # (S,) mm


def segments_of(curves: CurveSet, mesh_faces: np.ndarray) -> Segments:
    """Segments with both end points in barycentrics of the segment's face (exact vertex-id mapping)."""
    counts = np.diff(curves.offsets)
    row_curve = np.repeat(np.arange(curves.count), counts)
    rows = np.flatnonzero(row_curve[1:] == row_curve[:-1]) if len(row_curve) else np.zeros(0, dtype=np.int64)
    face = curves.faces[rows]
    here = mesh_faces[face]  # (S, 3) vertex ids of the segment's face
    there = mesh_faces[curves.faces[rows + 1]]
    match = here[:, :, None] == there[:, None, :]  # corner i of here is corner j of there
    end_bary = np.einsum("sij,sj->si", match.astype(np.float64), curves.bary[rows + 1])
    seg_len = np.linalg.norm(curves.points[rows + 1] - curves.points[rows], axis=1)
    all_len = np.zeros(len(row_curve))
    all_len[rows + 1] = seg_len
    arc = np.cumsum(all_len)
    arc -= np.repeat(arc[curves.offsets[:-1]], counts) if len(row_curve) else 0.0
    return Segments(
        curve=row_curve[rows],
        row=rows,
        index=rows - curves.offsets[row_curve[rows]],
        face=face,
        start_bary=curves.bary[rows],
        end_bary=end_bary,
        start_arc=arc[rows],
        length=seg_len,
    )


def face_pairs(face_a: np.ndarray, face_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All index pairs ``(i, j)`` with ``face_a[i] == face_b[j]``, in a deterministic order."""
    order = np.argsort(face_a, kind="stable")
    sorted_a = face_a[order]
    lo = np.searchsorted(sorted_a, face_b, side="left")
    hi = np.searchsorted(sorted_a, face_b, side="right")
    counts = hi - lo
    j = np.repeat(np.arange(len(face_b)), counts)
    start = np.repeat(lo - np.cumsum(np.r_[0, counts[:-1]]), counts)
    i = order[start + np.arange(counts.sum())]
    return i, j


def intersect(sa: Segments, sb: Segments, points_a: np.ndarray, layer_a: str, layer_b: str, same: bool) -> Crossings:
    """Crossings of every segment of ``sa`` with every segment of ``sb`` in the same face."""
    i, j = face_pairs(sa.face, sb.face)
    if same:
        keep = sa.curve[i] < sb.curve[j]
        i, j = i[keep], j[keep]
    a0, a1 = sa.start_bary[i, 1:], sa.end_bary[i, 1:]
    b0, b1 = sb.start_bary[j, 1:], sb.end_bary[j, 1:]
    r, q, w = a1 - a0, b1 - b0, b0 - a0
    denom = r[:, 0] * q[:, 1] - r[:, 1] * q[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (w[:, 0] * q[:, 1] - w[:, 1] * q[:, 0]) / denom
        t = (w[:, 0] * r[:, 1] - w[:, 1] * r[:, 0]) / denom
    hit = (denom != 0.0) & (s >= 0.0) & (s < 1.0) & (t >= 0.0) & (t < 1.0)
    i, j, s, t = i[hit], j[hit], s[hit], t[hit]
    bary = sa.start_bary[i] + s[:, None] * (sa.end_bary[i] - sa.start_bary[i])
    ra = sa.row[i]
    points = points_a[ra] + s[:, None] * (points_a[ra + 1] - points_a[ra])
    order = np.lexsort((sa.start_arc[i] + s * sa.length[i], sb.curve[j], sa.curve[i]))
    i, j, s, t, bary, points = i[order], j[order], s[order], t[order], bary[order], points[order]
    return Crossings(
        layer_a=layer_a,
        layer_b=layer_b,
        curve_a=sa.curve[i].astype(np.int64),
        curve_b=sb.curve[j].astype(np.int64),
        seg_a=sa.index[i].astype(np.int64),
        seg_b=sb.index[j].astype(np.int64),
        arc_a=sa.start_arc[i] + s * sa.length[i],
        arc_b=sb.start_arc[j] + t * sb.length[j],
        points=points,
        faces=sa.face[i].astype(np.int64),
        bary=bary,
    )


def drop_near(crossings: Crossings, mesh_faces: np.ndarray, vertex_distance: np.ndarray, radius_mm: float) -> Crossings:
    """The crossings whose distance (``vertex_distance`` per vertex, interpolated by barycentrics) is at least ``radius_mm``."""
    distance = np.einsum("ki,ki->k", crossings.bary, vertex_distance[mesh_faces[crossings.faces]])
    far = distance >= radius_mm
    kept = {f.name: getattr(crossings, f.name)[far] for f in dataclasses.fields(crossings) if f.name not in ("layer_a", "layer_b")}
    return dataclasses.replace(crossings, **kept)


def find_crossings(a: CurveSet, b: CurveSet, mesh_faces: np.ndarray) -> Crossings:
    """Crossings between curve set ``a`` and ``b`` (a different layer, or the same set for self-crossings)."""
    sa = segments_of(a, mesh_faces)
    sb = sa if b is a else segments_of(b, mesh_faces)
    return intersect(sa, sb, a.points, a.layer, b.layer, same=b is a)


def pair_multiplicity(crossings: Crossings, count_a: int, count_b: int) -> np.ndarray:
    """(count_a, count_b) int64 matrix: how many times curve ``a`` crosses curve ``b``."""
    out = np.zeros((count_a, count_b), dtype=np.int64)
    np.add.at(out, (crossings.curve_a, crossings.curve_b), 1)
    return out


class CrossingsParams(NodeParams):
    singularity_exclusion_mm: float = Field(
        10.0, ge=0, description="same-layer crossings closer than this geodesic distance (mm) to a singularity of that layer are dropped"
    )


@node(
    "curves.crossings",
    params=CrossingsParams,
    inputs=("mesh", "tx", "rx", "tx_field", "rx_field"),
    outputs=("tx_rx", "tx_tx", "rx_rx"),
)
def crossings(
    params: CrossingsParams, mesh: Mesh, tx: CurveSet, rx: CurveSet, tx_field: DirectionField, rx_field: DirectionField
) -> dict[str, Crossings]:
    """Tx x Rx crossings (all, with seg/arc positions on both curves) and Tx x Tx / Rx x Rx crossings away from singularities."""
    radius = params.singularity_exclusion_mm
    return {
        "tx_rx": find_crossings(tx, rx, mesh.faces),
        "tx_tx": drop_near(find_crossings(tx, tx, mesh.faces), mesh.faces, tx_field.singular_distance(), radius),
        "rx_rx": drop_near(find_crossings(rx, rx, mesh.faces), mesh.faces, rx_field.singular_distance(), radius),
    }
