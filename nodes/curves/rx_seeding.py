"""Rx seeds: points on the apex line of the dipole loops, at equal arc length. Units: mm."""
from __future__ import annotations

import numpy as np

from ...graph.errors import UserError
from ..geometry.mesh_tables import MeshTables
from .connection import DirectionField


def zero_set(tables: MeshTables, values: np.ndarray, faces_allowed: np.ndarray):
    """Zero level set of piecewise-linear vertex ``values`` inside ``faces_allowed``, as chained segments.

    A vertex where the value is exactly 0 counts as positive (the level set of ``values + epsilon``),
    so a level set through a vertex stays one chain. Each segment runs with the values increasing to
    its left (seen from outside, faces wound counter-clockwise). Returns per segment (in chain order):
    face (s,), end points ``p``, ``q`` (s, 3).
    """
    faces = tables.faces
    negative = values[faces] < 0.0
    fidx = np.flatnonzero(negative.any(axis=1) & ~negative.all(axis=1) & faces_allowed)
    d, neg = values[faces[fidx]], negative[fidx]
    pts, eids, leaving, entering = [], [], [], []
    for i in range(3):  # the edge opposite corner i, walked counter-clockwise from corner a to b
        a, b = (i + 1) % 3, (i + 2) % 3
        hit = neg[:, a] != neg[:, b]
        t = np.where(hit, -d[:, a] / np.where(hit, d[:, b] - d[:, a], 1.0), 0.0)
        pa = tables.vertices[faces[fidx, a]]
        pb = tables.vertices[faces[fidx, b]]
        pts.append(np.where(t[:, None] == 1.0, pb, pa + t[:, None] * (pb - pa)))  # a zero vertex exactly
        eids.append(tables.face_edges[fidx, (i + 1) % 3])
        leaving.append(hit & neg[:, b])
        entering.append(hit & neg[:, a])
    pts, eids = np.stack(pts, axis=1), np.stack(eids, axis=1)
    rows = np.arange(len(fidx))
    # walking round the face, the segment starts where the values turn negative: they rise to its left
    first, last = np.argmax(np.stack(leaving, axis=1), axis=1), np.argmax(np.stack(entering, axis=1), axis=1)
    p, q = pts[rows, first], pts[rows, last]
    ep, eq = eids[rows, first], eids[rows, last]
    # chains: the segment starting on edge eq follows; start chains at segments nothing leads into
    by_start = {int(e): s for s, e in enumerate(ep)}
    has_pred = np.isin(ep, eq)
    order, seen = [], np.zeros(len(fidx), dtype=bool)
    for s0 in np.r_[np.flatnonzero(~has_pred), np.flatnonzero(has_pred)]:
        s = int(s0)
        while not seen[s]:
            seen[s] = True
            order.append(s)
            s = by_start.get(int(eq[s]), s)
    order = np.asarray(order, dtype=np.int64)
    order = order[np.any(p[order] != q[order], axis=1)]  # the walk round a zero vertex: no length
    return fidx[order], p[order], q[order]


def chain_walks(chain) -> list[tuple[np.ndarray, np.ndarray]]:
    """The runs of joined segments of a :func:`zero_set` chain, each as a walk: points (k + 1, 3) and
    the face of the segment leaving each point (the last point: its segment's face)."""
    faces, p, q = chain
    if len(faces) == 0:
        return []
    breaks = np.flatnonzero(np.linalg.norm(q[:-1] - p[1:], axis=1) > 1e-9) + 1
    return [(np.vstack([p[s:e], q[e - 1 : e]]), np.r_[faces[s:e], faces[e - 1]])
            for s, e in zip(np.r_[0, breaks], np.r_[breaks, len(faces)])]


def rx_seeds(tables: MeshTables, field: DirectionField, sensing: np.ndarray, n_curves: int):
    """Seeds on the apex line of the dipole loops: where the field is tangent to the geodesic circles
    around the dipole source (``u . grad d = 0``), inside the sensing faces, at equal arc length."""
    grad = np.einsum("fij,fi->fj", tables.bary_gradients, field.start_distance[tables.faces])
    radial = np.einsum("fj,fj->f", field.face_direction, grad)
    weights = np.zeros(len(tables.vertices))
    np.add.at(weights, tables.faces.reshape(-1), np.repeat(tables.areas, 3))
    vertex_value = np.zeros(len(tables.vertices))
    np.add.at(vertex_value, tables.faces.reshape(-1), np.repeat(radial * tables.areas, 3))
    vertex_value /= weights
    seg_face, p, q = zero_set(tables, vertex_value, sensing)
    if len(seg_face) == 0:
        raise UserError("the Rx dipole field has no loop apex inside the sensing region: check the base region and dipole")
    length = np.linalg.norm(q - p, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(length)])
    target = (np.arange(n_curves) + 0.5) / n_curves * cum[-1]
    j = np.clip(np.searchsorted(cum, target, side="right") - 1, 0, len(length) - 1)
    frac = np.clip((target - cum[j]) / np.where(length[j] > 0, length[j], 1.0), 0.0, 1.0)
    points = p[j] + frac[:, None] * (q[j] - p[j])
    faces = seg_face[j]
    bary = np.maximum(tables.bary_of_points(faces, points), 1e-6)
    return faces, bary / bary.sum(axis=1, keepdims=True)
