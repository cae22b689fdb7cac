"""Synthetic layouts for the fabrication tests and benchmark: plane sections of a mesh as curves.

Tx curves are meridians (half-plane sections through the z axis, oriented top -> bottom), Rx curves
are horizontal sections (z = const) opened into arcs; crossings are computed on shared faces. The
rows follow the ``CurveSet`` convention of ``retrotouch.nodes.data.types``: row k lies on the edge
the curve crosses and carries barycentrics of the face it enters; segment k lies in ``faces[k]``.
"""
from __future__ import annotations

import numpy as np

from retrotouch.nodes.data.types import CurveSet, Crossings, Layout, Mesh


def _edge_point_bary(face: np.ndarray, a: int, b: int, t: float) -> np.ndarray:
    """Barycentrics w.r.t. ``face`` of the point (1 - t) * V[a] + t * V[b]."""
    w = np.zeros(3)
    w[list(face).index(a)] = 1.0 - t
    w[list(face).index(b)] = t
    return w


def plane_loops(mesh: Mesh, normal: np.ndarray, offset: float) -> list[tuple[list, list]]:
    """Closed section loops of the plane ``normal . x = offset``: (edges [(a, b, t)], faces) each;
    face ``faces[i]`` lies between ``edges[i]`` and ``edges[(i + 1) % m]``."""
    V, F = mesh.vertices, mesh.faces
    d = V @ normal - offset
    while np.abs(d).min() < 1e-9:
        offset += 1e-6
        d = V @ normal - offset
    above = d > 0
    crossing = np.nonzero(above[F].any(axis=1) & ~above[F].all(axis=1))[0]
    edge_faces: dict[tuple[int, int], list[int]] = {}
    face_edges: dict[int, list[tuple[int, int]]] = {}
    for f in crossing.tolist():
        tri = F[f].tolist()
        for i in range(3):
            a, b = tri[i], tri[(i + 1) % 3]
            if above[a] != above[b]:
                key = (min(a, b), max(a, b))
                edge_faces.setdefault(key, []).append(f)
                face_edges.setdefault(f, []).append(key)
    visited: set[int] = set()
    loops = []
    for start in crossing.tolist():
        if start in visited:
            continue
        edges, faces = [], []
        entry = face_edges[start][0]
        f = start
        while f not in visited:
            visited.add(f)
            a, b = entry
            edges.append((a, b, float(d[a] / (d[a] - d[b]))))
            faces.append(f)
            exit_edge = [e for e in face_edges[f] if e != entry][0]
            f = [g for g in edge_faces[exit_edge] if g != f][0]
            entry = exit_edge
        loops.append((edges, faces))
    return loops


def chain_rows(mesh: Mesh, edges: list, faces: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CurveSet rows (points, faces, bary) of an open chain: len(edges) == len(faces) + 1."""
    F, V = mesh.faces, mesh.vertices
    row_faces = list(faces) + [faces[-1]]
    bary = np.array([_edge_point_bary(F[f], a, b, t) for (a, b, t), f in zip(edges, row_faces)])
    points = np.einsum("rk,rkd->rd", bary, V[F[row_faces]])
    return points, np.asarray(row_faces, dtype=np.int64), bary


def curve_set(layer: str, chains: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> CurveSet:
    points = np.concatenate([c[0] for c in chains])
    lengths = np.array([np.linalg.norm(np.diff(c[0], axis=0), axis=1).sum() for c in chains])
    return CurveSet(
        layer=layer,
        points=points,
        faces=np.concatenate([c[1] for c in chains]),
        bary=np.concatenate([c[2] for c in chains]),
        offsets=np.concatenate([[0], np.cumsum([len(c[0]) for c in chains])]).astype(np.int64),
        lengths_mm=lengths,
        end_reason=np.zeros(len(chains), dtype=np.int8),
        angle=0.0,
    )


def _cyclic(seq: list, start: int, count: int) -> list:
    return [seq[(start + i) % len(seq)] for i in range(count)]


def meridian(mesh: Mesh, theta: float) -> tuple:
    """Longest run of the half-plane section at azimuth ``theta`` (radians), top -> bottom."""
    direction = np.array([np.cos(theta), np.sin(theta), 0.0])
    normal = np.array([-np.sin(theta), np.cos(theta), 0.0])
    best = None
    for edges, faces in plane_loops(mesh, normal, 0.0):
        V = mesh.vertices
        pts = np.array([(1 - t) * V[a] + t * V[b] for a, b, t in edges])
        inside = pts @ direction > 0
        m = len(edges)
        if inside.all() or not inside.any():
            continue
        starts = [i for i in range(m) if inside[i] and not inside[i - 1]]
        for s in starts:
            n = 0
            while inside[(s + n) % m]:
                n += 1
            if best is None or n > len(best[0]):
                best = (_cyclic(edges, s, n), _cyclic(faces, s, n - 1))
    edges, faces = best
    points = np.array([(1 - t) * mesh.vertices[a] + t * mesh.vertices[b] for a, b, t in edges])
    if points[0, 2] < points[-1, 2]:
        edges, faces = edges[::-1], faces[::-1]
    return chain_rows(mesh, edges, faces)


def latitude(mesh: Mesh, z: float, keep: float = 0.85, cut_theta: float = 0.0) -> tuple:
    """Longest loop of the section z = const, opened at azimuth ``cut_theta`` keeping a ``keep``
    fraction of its rows, oriented counter-clockwise seen from +z."""
    edges, faces = max(plane_loops(mesh, np.array([0.0, 0.0, 1.0]), z), key=lambda loop: len(loop[0]))
    V = mesh.vertices
    pts = np.array([(1 - t) * V[a] + t * V[b] for a, b, t in edges])
    centre = pts.mean(axis=0)
    rel = pts - centre
    if np.sum(rel[:-1, 0] * rel[1:, 1] - rel[:-1, 1] * rel[1:, 0]) < 0:
        edges, faces = edges[::-1], faces[::-1][1:] + faces[::-1][:1]
        rel = rel[::-1]
    azimuth = np.arctan2(rel[:, 1], rel[:, 0])
    start = int(np.argmin(np.abs(np.angle(np.exp(1j * (azimuth - cut_theta))))))
    n = max(3, int(keep * len(edges)))
    return chain_rows(mesh, _cyclic(edges, start, n), _cyclic(faces, start, n - 1))


def crossings(tx: CurveSet, rx: CurveSet, mesh: Mesh) -> Crossings:
    """Tx x Rx crossings on shared faces, the first one per channel pair."""
    by_face: dict[int, list[tuple[int, int]]] = {}
    for j in range(rx.count):
        rows = rx.curve(j)
        for k in range(rows.stop - rows.start - 1):
            by_face.setdefault(int(rx.faces[rows.start + k]), []).append((j, k))
    rows_out: dict[tuple[int, int], tuple] = {}
    for i in range(tx.count):
        rows = tx.curve(i)
        arc_tx = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(tx.points[rows], axis=0), axis=1))])
        for k in range(rows.stop - rows.start - 1):
            f = int(tx.faces[rows.start + k])
            for j, kb in by_face.get(f, []):
                if (i, j) in rows_out:
                    continue
                p0, p1 = tx.points[rows.start + k], tx.points[rows.start + k + 1]
                rj = rx.curve(j)
                q0, q1 = rx.points[rj.start + kb], rx.points[rj.start + kb + 1]
                A = np.stack([p1 - p0, q0 - q1], axis=1)
                (s, t), *_ = np.linalg.lstsq(A, q0 - p0, rcond=None)
                if not (0 <= s < 1 and 0 <= t < 1):
                    continue
                point = p0 + s * (p1 - p0)
                corners = mesh.vertices[mesh.faces[f]]
                bary = np.linalg.lstsq(np.vstack([corners.T, np.ones(3)]), np.append(point, 1.0), rcond=None)[0]
                arc_rx = np.linalg.norm(np.diff(rx.points[rj], axis=0), axis=1)[:kb].sum()
                rows_out[(i, j)] = (
                    i, j, k, kb,
                    arc_tx[k] + s * np.linalg.norm(p1 - p0),
                    arc_rx + t * np.linalg.norm(q1 - q0),
                    point, f, bary,
                )
    keys = sorted(rows_out)
    col = list(zip(*[rows_out[key] for key in keys])) if keys else [[] for _ in range(9)]
    return Crossings(
        layer_a="tx",
        layer_b="rx",
        curve_a=np.asarray(col[0], dtype=np.int64),
        curve_b=np.asarray(col[1], dtype=np.int64),
        seg_a=np.asarray(col[2], dtype=np.int64),
        seg_b=np.asarray(col[3], dtype=np.int64),
        arc_a=np.asarray(col[4], dtype=np.float64),
        arc_b=np.asarray(col[5], dtype=np.float64),
        points=np.asarray(col[6], dtype=np.float64).reshape(-1, 3),
        faces=np.asarray(col[7], dtype=np.int64),
        bary=np.asarray(col[8], dtype=np.float64).reshape(-1, 3),
    )


def greedy_pads(points: np.ndarray, min_distance_mm: float) -> np.ndarray:
    """Pad flags: crossings kept greedily so that selected ones are >= min_distance_mm apart."""
    pad = np.zeros(len(points), dtype=bool)
    for k in range(len(points)):
        if not pad.any() or np.linalg.norm(points[pad] - points[k], axis=1).min() >= min_distance_mm:
            pad[k] = True
    return pad


def section_layout(mesh: Mesh, n_tx: int, n_rx: int, pad_distance_mm: float = 12.0, keep: float = 0.85) -> Layout:
    """``n_tx`` meridians x ``n_rx`` latitudes (evenly spaced over the middle of the z range)."""
    thetas = (np.arange(n_tx) + 0.37) * 2 * np.pi / n_tx
    tx = curve_set("tx", [meridian(mesh, th) for th in thetas])
    z0, z1 = mesh.vertices[:, 2].min(), mesh.vertices[:, 2].max()
    zs = z0 + (z1 - z0) * (np.arange(n_rx) + 1.0) / (n_rx + 1)
    rx = curve_set("rx", [latitude(mesh, z, keep=keep, cut_theta=0.1 + 0.5 * j) for j, z in enumerate(zs)])
    cells = crossings(tx, rx, mesh)
    return Layout(
        tx=tx,
        rx=rx,
        cells=cells,
        pad=greedy_pads(cells.points, pad_distance_mm),
        tx_source=np.arange(n_tx, dtype=np.int64),
        rx_source=np.arange(n_rx, dtype=np.int64),
    )


def mesh_from_trimesh(tm, source: str) -> Mesh:
    return Mesh(vertices=np.asarray(tm.vertices, dtype=np.float64), faces=np.asarray(tm.faces, dtype=np.int64), source=source)
