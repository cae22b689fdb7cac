"""A synthetic layout instance on a sphere (radius 50 mm), independent of the curve nodes.

Tx: meridians from near the north pole down to the base cap (theta = 150 deg) plus two slanted
"rogue" curves that cross neighbouring meridians (C1). Rx: rising spirals of both slopes from the
base rim (spirals of opposite slope cross: C1) plus "hook" curves that rise and fall back in
longitude and so cross some meridians twice (C2). Crossings are computed exactly in the
(theta, phi) chart and mapped to the icosphere by closest point, so this module checks itself:
every crossing point lies on both of its curves.
"""
from __future__ import annotations

import functools

import numpy as np
import trimesh

from retrotouch.nodes.data.types import Crossings, CurveEnd, CurveSet, Mesh
from retrotouch.nodes.geometry.triangles import areas, corners

RADIUS_MM = 50.0
BASE_THETA = np.deg2rad(150.0)
TOP_THETA = np.deg2rad(12.0)


@functools.lru_cache(maxsize=2)
def sphere_mesh(subdivisions: int = 4) -> Mesh:
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=RADIUS_MM)
    return Mesh(vertices=np.asarray(s.vertices, dtype=np.float64), faces=np.asarray(s.faces, dtype=np.int64),
                source="synthetic:icosphere")


def sensing_mask(mesh: Mesh) -> np.ndarray:
    centroid = mesh.vertices[mesh.faces].mean(axis=1)
    theta = np.arccos(np.clip(centroid[:, 2] / np.linalg.norm(centroid, axis=1), -1, 1))
    return theta < BASE_THETA


class Regions:
    """Stand-in for the regions node output: the layout nodes read ``sensing_faces`` and ``touch_faces``,
    the sensing map sink ``up``, the pose, the finger model and the distance from the base (the base is the
    cap below BASE_THETA, so the sphere rests on -z)."""

    def __init__(self, mesh: Mesh):
        self.sensing_faces = sensing_mask(mesh)
        self.up = np.array([0.0, 0.0, 1.0])
        theta = np.arccos(np.clip(mesh.vertices[:, 2] / np.linalg.norm(mesh.vertices, axis=1), -1, 1))
        self.base_distance_mm = RADIUS_MM * np.maximum(BASE_THETA - theta, 0.0)  # along the meridians
        self.pose_kind = "round"
        self.pose_reason = "stand-in: a sphere resting on -z"
        self.tipping_angle_deg = 0.0
        area = areas(corners(mesh.vertices, mesh.faces))
        self.base_area_fraction = float(area[~self.sensing_faces].sum() / area.sum())
        self.sensing_area_fraction = 1.0 - self.base_area_fraction
        self.tx_pole = "far"
        self.touch_faces = self.sensing_faces  # a sphere is touchable everywhere
        self.touch = {"finger_radius_mm": 5.0, "hand_radius_mm": 25.0, "finger_reach_mm": 70.0, "pitch_mm": 1.25, "share": 1.0}


def _to_xyz(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    return RADIUS_MM * np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)


def _locate(mesh: Mesh, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    points, _, faces = trimesh.proximity.closest_point(tm, xyz)
    bary = trimesh.triangles.points_to_barycentric(mesh.vertices[mesh.faces[faces]], points)
    bary = np.clip(bary, 0, None)
    bary /= bary.sum(axis=1, keepdims=True)
    return np.einsum("kc,kcd->kd", bary, mesh.vertices[mesh.faces[faces]]), faces.astype(np.int64), bary


def _curve_set(mesh: Mesh, layer: str, charts: list[np.ndarray], angle: float) -> CurveSet:
    """charts: per curve an (n, 2) polyline of (theta, phi)."""
    xyz = [_to_xyz(c[:, 0], c[:, 1]) for c in charts]
    offsets = np.concatenate([[0], np.cumsum([len(p) for p in xyz])]).astype(np.int64)
    points, faces, bary = _locate(mesh, np.concatenate(xyz))
    lengths = np.array([np.linalg.norm(np.diff(points[offsets[i]:offsets[i + 1]], axis=0), axis=1).sum()
                        for i in range(len(charts))])
    return CurveSet(layer=layer, points=points, faces=faces, bary=bary, offsets=offsets, lengths_mm=lengths,
                    end_reason=np.full(len(charts), int(CurveEnd.BASE), dtype=np.int8), angle=angle,
                    family="dipole" if layer == "rx" else "field")


def _segment_hits(p: np.ndarray, q: np.ndarray) -> list[tuple[int, int, float, float]]:
    """Proper crossings between polylines p and q in the chart: (seg_p, seg_q, t_p, t_q)."""
    a0, da = p[:-1, None, :], (p[1:] - p[:-1])[:, None, :]
    b0, db = q[None, :-1, :], (q[1:] - q[:-1])[None, :, :]
    den = da[..., 0] * db[..., 1] - da[..., 1] * db[..., 0]
    w = b0 - a0
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * db[..., 1] - w[..., 1] * db[..., 0]) / den
        s = (w[..., 0] * da[..., 1] - w[..., 1] * da[..., 0]) / den
    hit = (np.abs(den) > 1e-15) & (t >= 0) & (t < 1) & (s >= 0) & (s < 1)
    return [(int(i), int(j), float(t[i, j]), float(s[i, j])) for i, j in zip(*np.nonzero(hit))]


def _crossings(mesh: Mesh, A: CurveSet, B: CurveSet, charts_a, charts_b, same: bool) -> Crossings:
    rows = []
    for ia, pa in enumerate(charts_a):
        for ib, pb in enumerate(charts_b):
            if same and ib <= ia:
                continue
            for shift in (-2 * np.pi, 0.0, 2 * np.pi):
                qb = pb + np.array([0.0, shift])
                for sa, sb, ta, tb in _segment_hits(pa, qb):
                    theta = pa[sa, 0] + ta * (pa[sa + 1, 0] - pa[sa, 0])
                    phi = pa[sa, 1] + ta * (pa[sa + 1, 1] - pa[sa, 1])
                    rows.append((ia, ib, sa, sb, ta, tb, theta, phi))
    if not rows:
        z = np.zeros(0, dtype=np.int64)
        return Crossings(A.layer, B.layer, z, z, z, z, z * 1.0, z * 1.0, np.zeros((0, 3)), z, np.zeros((0, 3)))
    r = np.array(rows)
    ca, cb, sa, sb = (r[:, i].astype(np.int64) for i in range(4))
    pts, faces, bary = _locate(mesh, _to_xyz(r[:, 6], r[:, 7]))

    def arc(cs: CurveSet, curve, seg, t):
        out = []
        for c, s, tt in zip(curve, seg, t):
            P = cs.points[cs.curve(int(c))]
            steps = np.linalg.norm(np.diff(P, axis=0), axis=1)
            out.append(steps[:s].sum() + tt * steps[s])
        return np.array(out)

    return Crossings(A.layer, B.layer, ca, cb, sa, sb, arc(A, ca, sa, r[:, 4]), arc(B, cb, sb, r[:, 5]),
                     pts, faces, bary)


def synthetic_instance(n_tx: int = 24, n_rx: int = 16, subdivisions: int = 4, steps: int = 60):
    """(mesh, regions, tx, rx, tx_rx, tx_tx, rx_rx) on the sphere."""
    mesh = sphere_mesh(subdivisions)
    t = np.linspace(0.0, 1.0, steps)
    tx_charts = []
    for i in range(n_tx):
        phi = 2 * np.pi * i / n_tx
        tx_charts.append(np.stack([TOP_THETA + t * (BASE_THETA - TOP_THETA), np.full_like(t, phi)], axis=1))
    for phi0 in (0.3, 3.4):  # rogue slanted Tx curves crossing a few meridians (C1)
        tx_charts.append(np.stack([np.deg2rad(40) + t * np.deg2rad(100), phi0 + t * 0.8], axis=1))
    rx_charts = []
    for j in range(n_rx):
        psi = 2 * np.pi * j / n_rx
        slope = 1.2 if j % 2 == 0 else -1.2
        theta = BASE_THETA - t * (BASE_THETA - np.deg2rad(25 + 40 * (j % 3) / 2))
        rx_charts.append(np.stack([theta, psi + slope * t], axis=1))
    for psi in (0.5, 2.6, 4.7):  # hooks crossing meridians twice (C2)
        theta = BASE_THETA - np.sin(np.pi * t) * np.deg2rad(70)
        rx_charts.append(np.stack([theta, psi + 0.9 * np.sin(np.pi * t)], axis=1))
    tx = _curve_set(mesh, "tx", tx_charts, 0.0)
    rx = _curve_set(mesh, "rx", rx_charts, np.deg2rad(10.0))
    return (mesh, Regions(mesh), tx, rx,
            _crossings(mesh, tx, rx, tx_charts, rx_charts, False),
            _crossings(mesh, tx, tx, tx_charts, tx_charts, True),
            _crossings(mesh, rx, rx, rx_charts, rx_charts, True))


def test_synthetic_crossings_lie_on_both_curves():
    mesh, _, tx, rx, tx_rx, tx_tx, rx_rx = synthetic_instance()
    for A, B, X in ((tx, rx, tx_rx), (tx, tx, tx_tx), (rx, rx, rx_rx)):
        assert len(X.curve_a) > 0
        for k in range(len(X.curve_a)):
            for cs, c in ((A, X.curve_a[k]), (B, X.curve_b[k])):
                P = cs.points[cs.curve(int(c))]
                assert np.min(np.linalg.norm(P - X.points[k], axis=1)) < 4.0  # within one chart step
    pairs = tx_rx.curve_a * rx.count + tx_rx.curve_b
    assert np.bincount(pairs).max() == 2  # the hooks cross some meridians twice
