"""From raw Muca frames to 3D touch points on the object (paper section 8).

Per frame (``TouchProcessor.process``):

1. **Baseline**: the first ``calibration_frames`` frames (no touch assumed) give each cell's
   baseline and noise sigma. Afterwards a common-mode term (median relative offset of the quiet
   cells) removes global drift at once, and each quiet cell's baseline follows the raw counts with
   time constant ``baseline_tau_s``. Cells near an active touch are *held* (not updated) while
   touched; a cell held longer than ``max_hold_s`` is re-baselined (a stuck touch fades). A cell
   reading far below its baseline for ``negative_reset_frames`` frames is re-baselined (a finger
   that rested on it at start-up).
2. **Detection**: ``delta = raw - baseline`` in counts (a touch raises counts on FT5x16 raw output).
   A cell turns on above ``on_sigma`` noise sigmas and stays on above ``off_sigma`` (hysteresis).
3. **Contact areas**: the deltas are interpolated over the vertices of a simplified copy of the mesh
   (``contact_mesh_faces``; Gaussian kernel, Nadaraya-Watson); vertices above the off threshold form
   connected components over the mesh edges. Each component is split among its touch peaks (active
   cells whose gain-normalised deltas are local maxima and are not explained by a stronger peak's
   coupling tail under the current coupling profile); the intensity-weighted, area-weighted centroid
   of each part, projected on the surface, is the coarse touch point, and the part's area above half
   of its peak intensity is the contact area.
4. **Sub-cell refinement** (``refine``): the coupling model ``delta_i = g_i A K(|p - x_i|)``
   (``g_i`` = 1 with a pad, ``no_pad_gain`` without; ``K`` the radial coupling profile,
   :mod:`retrotouch.nodes.sensing.coupling_profile`) fitted by maximum likelihood (Levenberg-Marquardt on
   the deltas of every crossing near the peak, dark ones included) with the finger kept on the
   surface; weak priors (offset ~ N(0, pitch^2), amplitude learned from well-posed touches) keep
   directions that a sparse layout does not resolve bounded. With several touches each one is
   refitted to the deltas minus the others' fitted coupling, starting from its first fit; peaks
   whose first fits land within a finger's width (2 ``finger_radius``) of a stronger one's are one
   finger. ``K`` starts as the Gaussian of width ``s = sqrt(finger_radius^2 + (pitch/2)^2)``;
   with ``adapt_coupling`` the width is calibrated from the first touches many crossings see
   (log-quadratic fits), then the shape, in units of that width, is learned from well-posed single
   touches: a board whose coupling is not a Gaussian (flat top, heavy tail) is localized without
   the bias of the wrong shape. Without a crossing above 2 sigma near the peak the coarse point stays.
5. **Tracking**: touches are matched to the previous frame's tracks by minimum total distance
   (``scipy.optimize.linear_sum_assignment``) within ``track_gate_mm``; unmatched touches get fresh
   ids, unmatched tracks end.

Units: mm for lengths, seconds for times inside (ms only in params named ``*_ms``), counts for
capacitance. Touch points lie on the mesh (``face`` + ``bary`` follow the datatypes conventions).
"""
from __future__ import annotations

import collections
import dataclasses
import hashlib
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp
import trimesh
from pydantic import Field
from scipy.optimize import linear_sum_assignment
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ...graph.errors import UserError
from ...graph.node import NodeParams
from .coupling_profile import CouplingProfile, ProfileLearner
from ..data.types import SENSING_MAP_FORMAT
from .muca_serial import NUM_RX, NUM_TX

FIT_ITERATIONS = 8  # Levenberg-Marquardt iterations per tangent plane (it stops earlier once steps are < 0.05 mm)
SURFACE_ROUNDS = 2  # tangent planes the coupling fit re-linearises in (it stops once the projection moves < 0.05 mm)
NORMAL_RIDGE = 0.05  # ridge on the fit's normal component, relative to the in-plane information
COUPLING_MIN_ESTIMATES = 30  # width estimates whose median becomes the coupling width
COUPLING_MIN_CELLS = 7  # crossings with signal a touch needs to give a width estimate
AMPLITUDE_WINDOW = 300  # well-posed fits whose amplitudes make up the amplitude prior
AMPLITUDE_MIN_ESTIMATES = 20  # well-posed fits needed before the amplitude prior applies
AMPLITUDE_WELL_POSED_MM = 0.5  # tangential 1-sigma (from the data alone) of a fit whose amplitude is learned


# --------------------------------------------------------------------------------------------
# Sensing map


@dataclasses.dataclass(frozen=True)
class SensingMap:
    """A layout as the runtime sees it: the mesh (mm) and, per cell, its channels and 3D crossing."""

    vertices: np.ndarray  # (n, 3) float64, mm
    faces: np.ndarray  # (m, 3) int64
    num_tx: int  # Tx channels wired (<= the board's 21)
    num_rx: int  # Rx channels wired (<= the board's 12)
    cell_tx: np.ndarray  # (K,) int64
    cell_rx: np.ndarray  # (K,) int64
    cell_points: np.ndarray  # (K, 3) float64, mm
    cell_faces: np.ndarray  # (K,) int64
    cell_bary: np.ndarray  # (K, 3) float64
    cell_normals: np.ndarray  # (K, 3) float64, unit
    cell_pad: np.ndarray  # (K,) bool
    source: str  # the sensing_map.json it came from

    @property
    def cell_count(self) -> int:
        return len(self.cell_tx)

    @property
    def frame_index(self) -> np.ndarray:
        """Index of each cell in a flattened channel-order board frame (``tx * 12 + rx`` on a Muca board,
        whatever number of channels the layout wires)."""
        return self.cell_tx * NUM_RX + self.cell_rx

    def pitch_mm(self) -> float:
        """Median distance from a cell to its nearest neighbour cell (mm)."""
        distances, _ = cKDTree(self.cell_points).query(self.cell_points, k=2)
        return float(np.median(distances[:, 1]))


def resolve_sensing_map_path(path: str | Path) -> Path:
    """A sensing_map.json or a run folder holding one -> the json path (UserError if neither)."""
    path = Path(path)
    if path.is_dir():
        path = path / "sensing_map.json"
    if not path.is_file():
        raise UserError(f"sensing map {path} not found: pass --layout <run folder or sensing_map.json>")
    return path


def load_sensing_map(path: str | Path) -> SensingMap:
    """Read ``sensing_map.json`` (datatypes.SENSING_MAP_FORMAT) and its mesh; one-line UserError on
    a missing file, a bad schema or a mesh that does not match the recorded sha256."""
    path = resolve_sensing_map_path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise UserError(f"sensing map {path} is not valid JSON ({exc}): regenerate it with the pipeline") from None
    if not isinstance(doc, dict) or doc.get("format") != SENSING_MAP_FORMAT:
        found = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise UserError(f"sensing map {path} has format {found!r}, expected {SENSING_MAP_FORMAT!r}")
    try:
        mesh_file = path.parent / doc["mesh"]["file"]
        num_tx, num_rx = int(doc["tx_channels"]), int(doc["rx_channels"])
        cells = doc["cells"]
        cell_tx = np.array([c["tx"] for c in cells], dtype=np.int64)
        cell_rx = np.array([c["rx"] for c in cells], dtype=np.int64)
        points = np.array([c["point"] for c in cells], dtype=np.float64).reshape(-1, 3)
        faces_k = np.array([c["face"] for c in cells], dtype=np.int64)
        bary = np.array([c["bary"] for c in cells], dtype=np.float64).reshape(-1, 3)
        normals = np.array([c["normal"] for c in cells], dtype=np.float64).reshape(-1, 3)
        pad = np.array([bool(c.get("pad", True)) for c in cells], dtype=bool)
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"sensing map {path} misses or mangles field {exc}: regenerate it with the pipeline") from None
    if len(cells) == 0:
        raise UserError(f"sensing map {path} lists no cells: the layout has no Tx/Rx crossings")
    if num_tx > NUM_TX or num_rx > NUM_RX:
        raise UserError(f"sensing map {path} wires {num_tx} x {num_rx} channels but the Muca board has {NUM_TX} x {NUM_RX}")
    if cell_tx.min() < 0 or cell_tx.max() >= num_tx or cell_rx.min() < 0 or cell_rx.max() >= num_rx:
        raise UserError(f"sensing map {path} has cell channels outside {num_tx} x {num_rx}")
    if len(np.unique(cell_tx * num_rx + cell_rx)) != len(cells):
        raise UserError(f"sensing map {path} lists a (tx, rx) pair twice")
    if not mesh_file.is_file():
        raise UserError(f"mesh {mesh_file} named by {path} not found: keep mesh.ply next to sensing_map.json")
    expected = doc["mesh"].get("sha256")
    if expected and hashlib.sha256(mesh_file.read_bytes()).hexdigest() != expected:
        raise UserError(f"mesh {mesh_file} does not match the sha256 in {path}: re-run the pipeline")
    mesh = trimesh.load(mesh_file, process=False, force="mesh")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if faces_k.max() >= len(faces):
        raise UserError(f"sensing map {path} names face {faces_k.max()} but {mesh_file} has {len(faces)} faces")
    return SensingMap(vertices, faces, num_tx, num_rx, cell_tx, cell_rx, points, faces_k, bary,
                      normals / np.linalg.norm(normals, axis=1, keepdims=True), pad, str(path))


def write_sensing_map(
    folder: str | Path,
    vertices: np.ndarray,
    faces: np.ndarray,
    cell_tx: np.ndarray,
    cell_rx: np.ndarray,
    cell_faces: np.ndarray,
    cell_bary: np.ndarray,
    num_tx: int = 21,
    num_rx: int = 12,
) -> Path:
    """Write ``mesh.ply`` + ``sensing_map.json`` (same schema as the pipeline's sink) into ``folder``;
    cell points and normals are computed exactly from faces/bary. Returns the json path."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh_bytes = trimesh.exchange.ply.export_ply(mesh, encoding="binary")
    (folder / "mesh.ply").write_bytes(mesh_bytes)
    points = np.einsum("kj,kjd->kd", cell_bary, vertices[faces[cell_faces]])
    normals = mesh.face_normals[cell_faces]
    channels = {
        layer: [{"channel": c, "name": f"{layer.capitalize()}{c:02d}", "curve": c,
                 "length_mm": round(_channel_length(points[ids == c]), 3)} for c in range(count)]
        for layer, ids, count in (("tx", cell_tx, num_tx), ("rx", cell_rx, num_rx))
    }
    doc = {
        "format": SENSING_MAP_FORMAT,
        "units": "mm",
        "mesh": {"file": "mesh.ply", "sha256": hashlib.sha256(mesh_bytes).hexdigest(),
                 "vertices": len(vertices), "faces": len(faces)},
        "tx_channels": num_tx,
        "rx_channels": num_rx,
        "channels": channels,
        "cells": [{"tx": int(t), "rx": int(r), "point": p.tolist(), "face": int(f), "bary": b.tolist(),
                   "normal": n.tolist(), "pad": True}
                  for t, r, p, f, b, n in zip(cell_tx, cell_rx, points, cell_faces, cell_bary, normals)],
    }
    path = folder / "sensing_map.json"
    path.write_text(json.dumps(doc), encoding="utf-8")
    return path


def _channel_length(points: np.ndarray) -> float:
    """Length of the polyline through a channel's crossings ordered greedily (a synthetic stand-in)."""
    if len(points) < 2:
        return 0.0
    order = [0]
    rest = list(range(1, len(points)))
    while rest:
        last = points[order[-1]]
        nearest = min(rest, key=lambda i: float(np.sum((points[i] - last) ** 2)))
        order.append(nearest)
        rest.remove(nearest)
    return float(np.sum(np.linalg.norm(np.diff(points[order], axis=0), axis=1)))


# --------------------------------------------------------------------------------------------
# Surface helpers


def closest_points_on_triangles(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Barycentrics (n, 3) of the closest point on triangle ``triangles[i]`` (n, 3, 3) to
    ``points[i]`` (n, 3) (Ericson's region test, vectorised)."""
    a = triangles[:, 0]
    ab, ac = triangles[:, 1] - a, triangles[:, 2] - a
    return _closest_barycentrics(points - a, ab, ac, np.einsum("ij,ij->i", ab, ab), np.einsum("ij,ij->i", ab, ac),
                                 np.einsum("ij,ij->i", ac, ac))


def _closest_barycentrics(ap, ab, ac, ab_ab, ab_ac, ac_ac) -> np.ndarray:
    """:func:`closest_points_on_triangles` from the offsets ``ap = p - a`` (n, 3), the edges ``ab``,
    ``ac`` (n, 3) and their dot products (n,) (a projector precomputes the last five per face)."""
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    d3, d4 = d1 - ab_ab, d2 - ab_ac  # ab.(p - b), ac.(p - b)
    d5, d6 = d1 - ab_ac, d2 - ac_ac  # ab.(p - c), ac.(p - c)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        v_ab = d1 / (d1 - d3)
        w_ac = d2 / (d2 - d6)
        w_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        total = va + vb + vc
        v_in, w_in = vb / total, vc / total
    # Regions in reverse priority, so the first matching test of Ericson's order wins.
    v, w = v_in, w_in
    edge_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    v, w = np.where(edge_bc, 1 - w_bc, v), np.where(edge_bc, w_bc, w)
    edge_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    v, w = np.where(edge_ac, 0.0, v), np.where(edge_ac, w_ac, w)
    corner_c = (d6 >= 0) & (d5 <= d6)
    v, w = np.where(corner_c, 0.0, v), np.where(corner_c, 1.0, w)
    edge_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    v, w = np.where(edge_ab, v_ab, v), np.where(edge_ab, 0.0, w)
    corner_b = (d3 >= 0) & (d4 <= d3)
    v, w = np.where(corner_b, 1.0, v), np.where(corner_b, 0.0, w)
    corner_a = (d1 <= 0) & (d2 <= 0)
    v, w = np.where(corner_a, 0.0, v), np.where(corner_a, 0.0, w)
    return np.column_stack([1 - v - w, v, w])


class SurfaceProjector:
    """Closest point on the mesh for query points near it (among the k faces nearest by centroid)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, k: int = 12):
        self.vertices, self.faces = vertices, faces
        self.triangles = vertices[faces]
        centroids = self.triangles.mean(axis=1)
        self.tree = cKDTree(centroids)
        self._origin = self.triangles[:, 0]
        self._ab, self._ac = self.triangles[:, 1] - self._origin, self.triangles[:, 2] - self._origin
        self._ab_ab = np.einsum("ij,ij->i", self._ab, self._ab)
        self._ab_ac = np.einsum("ij,ij->i", self._ab, self._ac)
        self._ac_ac = np.einsum("ij,ij->i", self._ac, self._ac)
        self.k = min(k, len(faces))
        normals = np.cross(self.triangles[:, 1] - self.triangles[:, 0], self.triangles[:, 2] - self.triangles[:, 0])
        self.face_normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
        helper = np.where(np.abs(self.face_normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        t1 = np.cross(self.face_normals, helper)
        t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
        self.face_frames = np.stack([t1, np.cross(self.face_normals, t1), self.face_normals], axis=1)  # rows t1, t2, n
        # Per-face rows as plain floats for the single-point path (numpy's per-call overhead dominates
        # on the k candidates of one point): origin, ab, ac, ab.ab, ab.ac, ac.ac, normal, and the
        # radius (largest vertex distance from the centroid: no point of the face is nearer a query
        # than its centroid distance minus the radius).
        radius = np.linalg.norm(self.triangles - centroids[:, None], axis=2).max(axis=1)
        self._face_rows = np.column_stack([self._origin, self._ab, self._ac, self._ab_ab, self._ab_ac, self._ac_ac,
                                           self.face_normals, radius]).tolist()

    def barycentrics_in_face(self, point: np.ndarray, face: int) -> np.ndarray | None:
        """Barycentrics (3,) of ``point`` (mm, in the plane of ``face``) when it lies inside the face,
        so that it is its own closest surface point; else None."""
        ox, oy, oz, abx, aby, abz, acx, acy, acz, ab_ab, ab_ac, ac_ac = self._face_rows[face][:12]
        px, py, pz = point.tolist()
        apx, apy, apz = px - ox, py - oy, pz - oz
        d1, d2 = abx * apx + aby * apy + abz * apz, acx * apx + acy * apy + acz * apz
        determinant = ab_ab * ac_ac - ab_ac * ab_ac
        if not determinant > 0.0:
            return None
        v, w = (ac_ac * d1 - ab_ac * d2) / determinant, (ab_ab * d2 - ab_ac * d1) / determinant
        if v < 0.0 or w < 0.0 or v + w > 1.0:
            return None
        return np.array([1.0 - v - w, v, w])

    def project(self, points: np.ndarray, facing: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(n, 3) points -> closest surface points (n, 3), their faces (n,), barycentrics (n, 3).

        With ``facing`` (3,), faces whose normal points away from it are skipped when others are
        near: on thin parts (ears, handles) the point lands on the side facing that way."""
        points = np.atleast_2d(points)
        if len(points) == 1:
            single = self._project_one(points[0], facing)
            if single is not None:
                return single
        _, candidates = self.tree.query(points, k=self.k)
        candidates = candidates.reshape(len(points), self.k)
        flat = candidates.ravel()
        origin, ab, ac = self._origin[flat], self._ab[flat], self._ac[flat]
        ap = (points[:, None] - origin.reshape(len(points), self.k, 3)).reshape(-1, 3)
        bary = _closest_barycentrics(ap, ab, ac, self._ab_ab[flat], self._ab_ac[flat], self._ac_ac[flat])
        closest = (origin + bary[:, 1:2] * ab + bary[:, 2:3] * ac).reshape(len(points), self.k, 3)
        distance2 = np.sum((closest - points[:, None]) ** 2, axis=2)
        if facing is not None:
            away = self.face_normals[candidates] @ facing <= 0.0
            distance2 = np.where(away & ~np.all(away, axis=1, keepdims=True), np.inf, distance2)
        best = np.argmin(distance2, axis=1)
        rows = np.arange(len(points))
        return closest[rows, best], candidates[rows, best], bary.reshape(len(points), self.k, 3)[rows, best]

    def _project_one(self, point: np.ndarray, facing: np.ndarray | None):
        """:meth:`project` of one point in plain floats: the same region tests (Ericson's order),
        products and sums as the vectorised path. None on a degenerate candidate (division by
        zero), which the vectorised path handles with its nan/inf semantics."""
        px, py, pz = point.tolist()
        centroid_distances, candidates = self.tree.query(point, k=self.k)
        centroid_distances, candidates = np.atleast_1d(centroid_distances).tolist(), np.atleast_1d(candidates).tolist()
        rows = self._face_rows
        if facing is not None:
            fx, fy, fz = np.asarray(facing, dtype=float).tolist()
            away = []
            for f in candidates:
                r = rows[f]
                away.append(r[12] * fx + r[13] * fy + r[14] * fz <= 0.0)
            if all(away):
                away = None
        else:
            away = None
        best = None
        best_d2 = np.inf
        try:
            for i, f in enumerate(candidates):
                row = rows[f]
                reach = centroid_distances[i] - row[15]
                if reach > 0.0 and reach * reach > best_d2:  # this face cannot be nearer than the best
                    continue
                ox, oy, oz, abx, aby, abz, acx, acy, acz, ab_ab, ab_ac, ac_ac = row[:12]
                apx, apy, apz = px - ox, py - oy, pz - oz
                # Summed in the order numpy's einsum uses for rows of 3, so the two paths agree bit for
                # bit (ties between faces sharing an edge then break the same way).
                d1 = (abx * apx + abz * apz) + aby * apy
                d2 = (acx * apx + acz * apz) + acy * apy
                d3, d4 = d1 - ab_ab, d2 - ab_ac
                d5, d6 = d1 - ab_ac, d2 - ac_ac
                if d1 <= 0 and d2 <= 0:
                    v = w = 0.0
                elif d3 >= 0 and d4 <= d3:
                    v, w = 1.0, 0.0
                else:
                    vc = d1 * d4 - d3 * d2
                    if vc <= 0 and d1 >= 0 and d3 <= 0:
                        v, w = d1 / (d1 - d3), 0.0
                    elif d6 >= 0 and d5 <= d6:
                        v, w = 0.0, 1.0
                    else:
                        vb = d5 * d2 - d1 * d6
                        if vb <= 0 and d2 >= 0 and d6 <= 0:
                            v, w = 0.0, d2 / (d2 - d6)
                        else:
                            va = d3 * d6 - d5 * d4
                            if va <= 0 and d4 - d3 >= 0 and d5 - d6 >= 0:
                                w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
                                v = 1 - w
                            else:
                                total = va + vb + vc
                                v, w = vb / total, vc / total
                cx, cy, cz = ox + v * abx + w * acx, oy + v * aby + w * acy, oz + v * abz + w * acz
                ex, ey, ez = cx - px, cy - py, cz - pz
                d2_point = ex * ex + ey * ey + ez * ez
                if away is not None and away[i]:
                    d2_point = np.inf
                if best is None or d2_point < best_d2:
                    best, best_d2 = (f, cx, cy, cz, 1 - v - w, v, w), d2_point
        except ZeroDivisionError:
            return None
        if best is None or not np.isfinite(best_d2):
            return None
        f, cx, cy, cz, b0, b1, b2 = best
        return np.array([[cx, cy, cz]]), np.array([f], dtype=np.intp), np.array([[b0, b1, b2]])


def median(values: np.ndarray) -> float:
    """Median of a small 1-D array of finite values (what ``np.median`` returns, at a tenth of its
    per-call overhead)."""
    ordered = np.sort(values)
    middle = len(ordered) // 2
    return float(ordered[middle]) if len(ordered) % 2 else float((ordered[middle - 1] + ordered[middle]) / 2)


def processing_mesh(vertices: np.ndarray, faces: np.ndarray, target_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """A simplified copy of the mesh (quadric edge collapse, topology kept) for contact areas; the
    mesh itself when it is already small enough."""
    if len(faces) <= target_faces:
        return vertices, faces
    import pymeshlab

    meshes = pymeshlab.MeshSet()
    meshes.add_mesh(pymeshlab.Mesh(vertices, faces))
    meshes.meshing_decimation_quadric_edge_collapse(targetfacenum=target_faces, preservetopology=True,
                                                   preservenormal=True, planarquadric=True)
    simplified = meshes.current_mesh()
    return simplified.vertex_matrix().astype(np.float64), simplified.face_matrix().astype(np.int64)


def vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """One third of the area of the faces around each vertex (mm^2)."""
    triangles = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), axis=1)
    return np.bincount(faces.ravel(), weights=np.repeat(area / 3.0, 3), minlength=len(vertices))


# --------------------------------------------------------------------------------------------
# Processing


class ProcessingParams(NodeParams):
    """Touch processing settings (counts, mm, seconds; see the module docstring)."""

    calibration_frames: int = Field(20, ge=2, description="frames averaged for the initial baseline")
    baseline_tau_s: float = Field(2.0, gt=0, description="drift tracking time constant of quiet cells (s)")
    noise_tau_s: float = Field(20.0, gt=0, description="noise sigma tracking time constant (s)")
    update_sigma: float = Field(3.0, gt=0, description="a cell updates its baseline only while |delta| < this x sigma")
    on_sigma: float = Field(6.0, gt=0, description="cell turns on above this many noise sigmas")
    off_sigma: float = Field(4.0, gt=0, description="an on cell stays on above this many noise sigmas")
    min_noise_counts: float = Field(0.5, gt=0, description="floor of the per-cell noise sigma (counts)")
    hold_radius_mm: float | None = Field(None, gt=0, description="cells this close to a touch hold their baseline; None: 2.5 x pitch")
    max_hold_s: float = Field(60.0, gt=0, description="a cell held longer is re-baselined (stuck touch)")
    negative_reset_frames: int = Field(10, ge=1, description="frames below -on threshold before a re-baseline")
    coupling_sigma_mm: float | None = Field(None, gt=0, description="width of the Gaussian the coupling profile starts from; None: sqrt(finger_radius^2 + (pitch/2)^2)")
    finger_radius_mm: float = Field(4.5, gt=0, description="finger contact radius used for the default coupling width")
    interpolation_radius_mm: float | None = Field(None, gt=0, description="vertex-to-cell interpolation radius; None: 1.5 x pitch")
    peak_radius_mm: float | None = Field(None, gt=0, description="a touch peak is the strongest cell within this radius; None: 1.5 x pitch")
    refine: bool = Field(True, description="refine the centroid with the coupling fit")
    no_pad_gain: float = Field(0.5, gt=0, description="coupling of a crossing without electrode pad relative to a padded one")
    adapt_coupling: bool = Field(True, description="learn the coupling width, then the profile's shape, from touches")
    contact_mesh_faces: int = Field(6000, ge=100, description="faces of the simplified mesh used for contact areas")
    track_gate_mm: float = Field(40.0, gt=0, description="largest move of one touch between frames (mm)")


@dataclasses.dataclass(frozen=True)
class Touch:
    """One touch point of one frame."""

    id: int  # stable across frames while the finger stays down
    point: np.ndarray  # (3,) mm, on the surface
    face: int
    bary: np.ndarray  # (3,)
    normal: np.ndarray  # (3,) unit outward face normal
    intensity: float  # peak delta (counts)
    area_mm2: float  # contact area (interpolated intensity >= half of the peak)
    peak_cell: int  # index into the sensing map's cells

    def as_json(self) -> dict[str, Any]:
        return {"id": self.id, "point": [round(x, 3) for x in self.point.tolist()], "face": self.face,
                "bary": [round(x, 5) for x in self.bary.tolist()], "normal": [round(x, 4) for x in self.normal.tolist()],
                "intensity": round(self.intensity, 1), "area_mm2": round(self.area_mm2, 1), "cell": self.peak_cell}


@dataclasses.dataclass(frozen=True)
class FrameResult:
    """What one frame produced: touches (with ids), their lifecycle events, and per-cell deltas."""

    t: float  # s
    calibrated: bool
    touches: tuple[Touch, ...]
    events: tuple[dict[str, Any], ...]  # touch_down / touch_move / touch_up, JSON-ready
    delta: np.ndarray  # (K,) counts after baseline removal (0 during calibration)
    active: np.ndarray  # (K,) bool, cells on


class TouchProcessor:
    """Stateful frame -> touches processing for one sensing map (see the module docstring)."""

    def __init__(self, sensing_map: SensingMap, params: ProcessingParams = ProcessingParams()):
        self.map = sensing_map
        self.params = params
        self.pitch = sensing_map.pitch_mm()
        self.coupling_sigma = params.coupling_sigma_mm or float(np.hypot(params.finger_radius_mm, self.pitch / 2))
        self.initial_coupling_sigma = self.coupling_sigma
        self._width_estimates: list[float] = []
        self._amplitude_estimates: collections.deque[float] = collections.deque(maxlen=AMPLITUDE_WINDOW)
        self._amplitude_prior: tuple[float, float] | None = None  # (log counts, sigma) of a padded crossing
        self._amplitude_count = 0  # well-posed fits seen
        self.hold_radius = params.hold_radius_mm or 2.5 * self.pitch
        self.peak_radius = params.peak_radius_mm or 1.5 * self.pitch
        interpolation_radius = params.interpolation_radius_mm or 1.5 * self.pitch
        cells = sensing_map.cell_points
        self.frame_index = sensing_map.frame_index
        self.cell_gain = np.where(sensing_map.cell_pad, 1.0, params.no_pad_gain)
        self.cell_distance = np.linalg.norm(cells[:, None] - cells[None], axis=2)
        self.coupling = ProfileLearner(CouplingProfile.gaussian(1.0))  # the shape, in units of the width
        self._use_profile()
        self.projector = SurfaceProjector(sensing_map.vertices, sensing_map.faces)
        self.contact_vertices, self.contact_faces = processing_mesh(sensing_map.vertices, sensing_map.faces,
                                                                    params.contact_mesh_faces)
        self.areas = vertex_areas(self.contact_vertices, self.contact_faces)
        edges = self.contact_faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        source, target = np.unique(np.concatenate([edges, edges[:, ::-1]]), axis=0).T  # sorted by source
        degree = np.bincount(source, minlength=len(self.contact_vertices))
        # (n, max degree) mesh neighbours of each contact vertex, padded with the vertex itself.
        self.vertex_neighbours = np.repeat(np.arange(len(degree))[:, None], max(int(degree.max()), 1), axis=1)
        self.vertex_neighbours[source, np.arange(len(source)) - (np.cumsum(degree) - degree)[source]] = target
        self._build_interpolation(interpolation_radius)
        neighbours = [np.flatnonzero((row <= self.peak_radius) & (row > 0)) for row in self.cell_distance]
        width = max(1, max(len(n) for n in neighbours))
        self.peak_neighbours = np.array([np.pad(n, (0, width - len(n)), constant_values=k) for k, n in enumerate(neighbours)])
        self.reset()

    def _use_profile(self) -> None:
        """Fit with the learned shape stretched to the learned width from now on; the peak test's
        tail bounds follow: a finger at most ``a = 0.6 pitch`` from a peak crossing (inside the sensed
        region) gives a crossing ``D`` from that peak at most ``K(max(D - a, 0)) / K(a)`` times the
        peak's delta."""
        profile = self.profile = self.coupling.profile.scaled(self.coupling_sigma)
        offset = 0.6 * self.pitch
        reach = profile.at_distance(np.maximum(self.cell_distance - offset, 0.0))
        self._tail_bound = reach / profile.at_distance(offset)

    def _build_interpolation(self, radius: float) -> None:
        """Sparse Nadaraya-Watson weights from cells to the vertices within ``radius`` of a cell."""
        vertices = self.contact_vertices
        cell_tree = cKDTree(self.map.cell_points)
        pairs = cell_tree.sparse_distance_matrix(cKDTree(vertices), radius, output_type="coo_matrix")
        bandwidth = self.pitch / 2
        weights = np.exp(-(pairs.data**2) / (2 * bandwidth**2))
        cell_to_vertex = sp.csr_matrix((weights, (pairs.row, pairs.col)), shape=(self.map.cell_count, len(vertices)))
        totals = np.asarray(cell_to_vertex.sum(axis=0)).ravel()
        self.vertex_to_cell = sp.csr_matrix(cell_to_vertex.T.multiply(1.0 / np.maximum(totals, 1e-300)[:, None]))

    def reset(self) -> None:
        """Forget baseline, noise and tracks (the next frames recalibrate)."""
        k = self.map.cell_count
        self._calibration: list[np.ndarray] = []
        self.baseline = np.zeros(k)
        self.noise = np.ones(k)
        self.active = np.zeros(k, dtype=bool)
        self._held_since = np.full(k, np.inf)
        self._below = np.zeros(k, dtype=np.int64)
        self._tracks: dict[int, np.ndarray] = {}
        self._next_id = 0
        self._last_t: float | None = None

    @property
    def calibrated(self) -> bool:
        return len(self._calibration) >= self.params.calibration_frames

    def process(self, values: np.ndarray, t: float) -> FrameResult:
        """One channel-order board frame ``(21, 12)`` at time ``t`` (s) -> :class:`FrameResult`."""
        raw = np.asarray(values, dtype=np.float64).ravel()[self.frame_index]
        valid = raw >= 0
        if not self.calibrated:
            return self._calibrate(raw, valid, t)
        dt = 0.1 if self._last_t is None else min(max(t - self._last_t, 1e-3), 1.0)
        self._last_t = t
        p = self.params
        sigma = self._sigma()
        delta = raw - self.baseline
        quiet = valid & (np.abs(delta) < p.update_sigma * sigma) & ~self.active & (self.baseline > 0)
        if np.count_nonzero(quiet) >= 3:
            common = median(delta[quiet] / self.baseline[quiet])
            delta = raw - self.baseline * (1.0 + common)
        delta[~valid] = 0.0
        threshold = np.where(self.active, p.off_sigma, p.on_sigma) * sigma
        self.active = valid & (delta > threshold)
        touches = self._touches(delta, sigma) if self.active.any() else []
        tracked, events = self._track(touches, t)
        self._update_baseline(raw, delta, valid, sigma, tracked, t, dt)
        return FrameResult(t, True, tuple(tracked), tuple(events), delta, self.active.copy())

    def _calibrate(self, raw: np.ndarray, valid: np.ndarray, t: float) -> FrameResult:
        self._calibration.append(raw)
        if self.calibrated:
            stack = np.array(self._calibration)
            self.baseline = stack.mean(axis=0)
            # 20 frames give a sigma within ~+-16 %: start no lower than the pooled median (cells of
            # one board share their noise floor); the running estimate refines it afterwards.
            spread = stack.std(axis=0, ddof=1)
            self.noise = np.maximum(spread, float(np.median(spread)))
            self._last_t = t
        k = self.map.cell_count
        return FrameResult(t, self.calibrated, (), (), np.zeros(k), np.zeros(k, dtype=bool))

    def _sigma(self) -> np.ndarray:
        floor = max(self.params.min_noise_counts, 0.5 * median(self.noise))
        return np.maximum(self.noise, floor)

    def _update_baseline(self, raw, delta, valid, sigma, touches, t, dt) -> None:
        p = self.params
        held = np.zeros(len(raw), dtype=bool)
        if touches:
            peaks = np.array([touch.peak_cell for touch in touches])
            held = np.any(self.cell_distance[:, peaks] <= self.hold_radius, axis=1)
        self._held_since = np.where(held, np.minimum(self._held_since, t), np.inf)
        stuck = held & (t - self._held_since > p.max_hold_s)
        self.baseline[stuck] = raw[stuck]
        self._held_since[stuck] = np.inf
        quiet = valid & ~held & (np.abs(delta) < p.update_sigma * sigma)
        alpha = 1.0 - np.exp(-dt / p.baseline_tau_s)
        self.baseline[quiet] += alpha * (raw[quiet] - self.baseline[quiet])
        beta = 1.0 - np.exp(-dt / p.noise_tau_s)
        self.noise[quiet] = np.sqrt((1 - beta) * self.noise[quiet] ** 2 + beta * delta[quiet] ** 2)
        below = valid & (delta < -p.on_sigma * sigma)
        self._below = np.where(below, self._below + 1, 0)
        reset = self._below >= p.negative_reset_frames
        self.baseline[reset] = raw[reset]
        self._below[reset] = 0

    # ---- contact areas and touch points

    def _peaks(self, delta: np.ndarray) -> np.ndarray:
        """Active cells that are local maxima and not explained by a stronger peak's coupling tail,
        both on gain-normalised deltas ``delta / g`` (a crossing without a pad reads less for the same
        finger: two padded crossings on either side of a finger over pad-less ones are not two touches).

        A candidate must exceed twice the tail bound (:meth:`_use_profile`) of every stronger peak.
        """
        delta = delta / self.cell_gain
        candidates = np.flatnonzero(self.active & (delta >= delta[self.peak_neighbours].max(axis=1)))
        candidates = candidates[np.argsort(-delta[candidates])]
        kept: list[tuple[int, float]] = []  # (cell, normalised delta), strongest first
        for c, value in zip(candidates.tolist(), delta[candidates].tolist()):
            bounds = self._tail_bound[c].tolist()  # plain floats for the loop
            if all(value > 2.0 * peak * bounds[k] for k, peak in kept):
                kept.append((c, value))
        return np.array([c for c, _ in kept], dtype=np.int64)

    def _touches(self, delta: np.ndarray, sigma: np.ndarray) -> list[Touch]:
        peaks = self._peaks(delta)
        if len(peaks) == 0:
            return []
        positive = np.maximum(delta, 0.0)
        field = self.vertex_to_cell @ positive
        floor = self.params.off_sigma * median(sigma)
        inside = field > floor
        region = np.flatnonzero(inside)
        if len(region) == 0:
            return []
        field = field[region]
        labels = self._component_labels(inside, region)
        vertices = self.contact_vertices[region]
        # Each vertex belongs to the nearest peak of its own component (components without a peak
        # drop); a peak's component is its nearest vertex's.
        peak_points = self.map.cell_points[peaks]
        d2 = np.sum((vertices[:, None] - peak_points[None]) ** 2, axis=2)
        peak_label = labels[np.argmin(d2, axis=0)]
        d2[labels[:, None] != peak_label[None]] = np.inf
        owner = np.argmin(d2, axis=1)
        owned = np.isfinite(d2[np.arange(len(region)), owner])
        found = []  # [cell, point, face, bary, area, centroid]; point/face/bary set by the refinement or below
        areas = self.areas[region]
        for j, cell in enumerate(peaks.tolist()):
            mine = np.flatnonzero(owned & (owner == j))
            if len(mine) == 0:
                continue
            mine_field, mine_areas = field[mine], areas[mine]
            weights = mine_areas * (mine_field - floor)
            centroid = weights @ vertices[mine] / weights.sum()
            area = float(mine_areas[mine_field >= 0.5 * mine_field.max()].sum())
            found.append([cell, None, None, None, area, centroid])
        if self.params.refine:
            self._refine_all(found, delta, sigma)
        for entry in found:
            if entry[1] is None:
                entry[1:4] = self._coarse_point(entry[5], entry[0])
        return [Touch(-1, point, face, bary, self.projector.face_normals[face], float(delta[cell]), area, cell)
                for cell, point, face, bary, area, _ in found]

    def _component_labels(self, inside: np.ndarray, region: np.ndarray) -> np.ndarray:
        """Connected-component labels of the contact vertices ``region`` (= ``flatnonzero(inside)``)
        over the mesh edges between them."""
        local = np.cumsum(inside, dtype=np.int32) - 1  # index in region
        neighbours = self.vertex_neighbours[region]
        linked = inside[neighbours]
        # A symmetric graph in CSR form: row k lists region vertex k's neighbours inside (and itself).
        targets = local[neighbours[linked]]
        rows = np.zeros(len(region) + 1, dtype=np.int32)
        np.cumsum(np.count_nonzero(linked, axis=1), out=rows[1:])
        graph = sp.csr_matrix((np.ones(len(targets)), targets, rows), shape=(len(region), len(region)))
        return connected_components(graph, directed=False)[1]

    def _coarse_point(self, centroid: np.ndarray, cell: int) -> tuple[np.ndarray, int, np.ndarray]:
        """The contact centroid projected on the surface on the side facing like the peak cell."""
        facing = self.map.cell_normals[cell]
        points, faces, barys = self.projector.project(centroid, facing)
        face = int(faces[0])
        if self.projector.face_normals[face] @ facing <= 0.0:
            # The centroid of a contact wrapping a thin part projected onto the far side.
            return self.map.cell_points[cell], int(self.map.cell_faces[cell]), self.map.cell_bary[cell]
        return points[0], face, barys[0]

    def _learn_coupling(self, offsets: np.ndarray, frame: np.ndarray, normalised: np.ndarray) -> None:
        """One estimate of the coupling width from a touch's strong crossings at ``offsets`` (k, 3) (mm)
        from its peak crossing, with gain-normalised deltas ``normalised`` (counts): with ``y_i`` the
        offsets in the face ``frame`` (rows t1, t2, n), ``log d_i = c + b.y_i / s^2 - a |y_i|^2`` is linear
        in (c, b, a) and ``s = sqrt(1 / (2 a))``. The median of the first ``COUPLING_MIN_ESTIMATES``
        estimates, kept within half to twice the initial width, becomes the width for good: the
        profile's shape is learned in units of it from then on."""
        full = np.empty((len(normalised), 5))
        full[:, 0] = 1.0
        full[:, 1:4] = offsets @ frame.T / self.coupling_sigma**2
        full[:, 4] = -np.einsum("ij,ij->i", offsets, offsets)
        weights = normalised * normalised
        normal_matrix = full.T @ (full * weights[:, None])
        normal_matrix[3, 3] += NORMAL_RIDGE * 0.5 * (normal_matrix[1, 1] + normal_matrix[2, 2])
        try:
            a = np.linalg.solve(normal_matrix, full.T @ (weights * np.log(normalised)))[4]
        except np.linalg.LinAlgError:
            return
        if a <= 0:
            return
        self._width_estimates.append(float(np.sqrt(1.0 / (2.0 * a))))
        if len(self._width_estimates) == COUPLING_MIN_ESTIMATES:
            learned = median(np.array(self._width_estimates))
            self.coupling_sigma = min(max(learned, 0.5 * self.initial_coupling_sigma), 2.0 * self.initial_coupling_sigma)
            self._use_profile()

    def _refine_all(self, found: list[list[Any]], delta: np.ndarray, sigma: np.ndarray) -> None:
        """Refine every touch in place (entries of ``found`` that are one finger are merged out).
        Each fit starts at its peak crossing (on the touched side, within a pitch of the finger);
        with several touches the first pass fits each one to its own cells (nearest to its peak),
        peaks whose fits land within ``2 finger_radius`` of a stronger one's are dropped (their area
        added to it), and a second pass fits each remaining touch to all deltas minus the other
        touches' fitted coupling, starting from its first fit's point and amplitude. The coupling
        profile learns from single touches and from second-pass fits (a first pass beside another
        touch carries that touch's tail)."""
        single = len(found) == 1
        fits: list[tuple[np.ndarray, float] | None] = []  # (point, log amplitude) of each first-pass fit
        peaks = np.array([entry[0] for entry in found])
        # First pass: each touch sees only the cells nearer its own peak than any other peak.
        nearest_peak = np.argmin(self.cell_distance[:, peaks], axis=1)
        for j, entry in enumerate(found):
            cell = entry[0]
            own_cells = delta if single else np.where(nearest_peak == j, delta, np.nan)
            refined = self._refine(self.map.cell_points[cell], int(self.map.cell_faces[cell]), own_cells, sigma,
                                   learn_profile=single)
            fits.append(None if refined is None else (refined[0], min(refined[3], 30.0)))
            if refined is not None:
                entry[1:4] = refined[:3]
        if single:
            return
        merge_mm = 2.0 * self.params.finger_radius_mm
        kept: list[int] = []  # found is strongest peak first
        for j, fit in enumerate(fits):
            same = None if fit is None else next((k for k in kept if fits[k] is not None
                                                  and math.dist(fits[k][0].tolist(), fit[0].tolist()) < merge_mm), None)
            if same is None:
                kept.append(j)
            else:
                found[same][4] += found[j][4]
        if len(kept) < len(found):
            found[:] = [found[j] for j in kept]
            fits = [fits[j] for j in kept]
            if len(found) == 1:  # one finger after all: fit it to every delta
                entry = found[0]
                refined = self._refine(self.map.cell_points[entry[0]], int(self.map.cell_faces[entry[0]]), delta, sigma,
                                       learn_profile=True)
                if refined is not None:
                    entry[1:4] = refined[:3]
                return
        if sum(fit is not None for fit in fits) < 2:
            return
        cells = self.map.cell_points
        modelled = [np.zeros(len(cells)) if fit is None else
                    self.cell_gain * math.exp(fit[1]) * self.profile.at_squared(np.sum((cells - fit[0]) ** 2, axis=1))[0]
                    for fit in fits]
        total = np.sum(modelled, axis=0)
        for entry, fit, own in zip(found, fits, modelled):
            if fit is None:
                continue
            others = total - own
            if not np.any(others > sigma):  # the others' coupling does not reach this touch's crossings
                continue
            refined = self._refine(entry[1], entry[2], delta - others, sigma, fit[1], learn_profile=True)
            if refined is not None:
                entry[1:4] = refined[:3]

    def _refine(self, point, face, values, sigma, log_amplitude=None, learn_profile=False):
        """Maximum-likelihood coupling fit around ``point`` (the peak crossing, or a first fit's point
        refitted from its log-amplitude ``log_amplitude``); returns (point, face, bary) on the surface
        and the fitted log-amplitude ``a`` (log counts), or None when no crossing near ``point``
        carries signal above 2 sigma.

        Model ``delta_i = g_i exp(a) K(|p - x_i|)`` over every crossing within ``3 s + pitch`` of the
        start (``s`` the coupling width), dark ones included (a crossing that reads nothing says the
        finger is not near it); residuals weighted by ``1 / sigma_i^2`` (the deltas' noise is
        additive, so this is the likelihood). The finger ``p`` stays on the surface: Levenberg-Marquardt
        steps ``(u, a)`` with ``u`` in the tangent plane of the current face, then ``p`` is projected
        back onto the surface on the side facing the same way and the fit repeats in the new tangent
        plane (``SURFACE_ROUNDS``). Priors keep directions the crossings do not resolve bounded (on a sparse
        layout three crossings can be nearly collinear, or only two see the finger):

        * ``u`` (offset from the start) ~ N(0, pitch^2): an unresolved direction stays at the peak crossing;
        * ``a`` ~ N(a0, sigma_a^2), once learned (``_learn_amplitude``) from well-posed fits: the peak
          crossing's delta then tells how far the finger is from it.

        A first fit (no ``log_amplitude``) starts ``a`` at the log of the largest gain-normalised
        delta, or at the amplitude prior's mean if higher. On thin parts (ears) and tips the strongest
        crossing can sit on the far side, so a first fit also starts from the two strongest crossings
        facing away (normals > 60 degrees apart, at least half the strongest gain-normalised delta) and
        keeps the lowest cost; a refit starts from its first fit only. A well-posed fit with
        ``learn_profile`` gives the coupling profile its (squared distance, delta / (g exp(a)),
        weight) pairs (:class:`~retrotouch.nodes.sensing.coupling_profile.ProfileLearner`).
        """
        cells = self.map.cell_points
        offsets = cells - point
        distance2 = np.einsum("ij,ij->i", offsets, offsets)
        near = np.flatnonzero((distance2 <= (3.0 * self.coupling_sigma + self.pitch) ** 2) & np.isfinite(values))
        d, g, x, noise = values[near], self.cell_gain[near], cells[near], sigma[near]
        strong = d > 2.0 * noise
        if not strong.any():
            return None
        width_learned = len(self._width_estimates) >= COUPLING_MIN_ESTIMATES
        if self.params.adapt_coupling and not width_learned:
            # Width estimates only from touches many crossings see around the peak (log-linear form).
            learn = strong & (distance2[near] <= (3.0 * self.coupling_sigma) ** 2)
            if np.count_nonzero(learn) >= COUPLING_MIN_CELLS:
                self._learn_coupling(offsets[near[learn]], self.projector.face_frames[face], d[learn] / g[learn])
        starts = [(point, face)]
        if log_amplitude is None:
            normalised = d / g
            facing = self.projector.face_normals[face]
            away = np.flatnonzero(strong & (self.map.cell_normals[near] @ facing < 0.5)
                                  & (normalised >= 0.5 * normalised[strong].max()))
            if len(away):
                for k in away[np.argsort(-normalised[away])][:2].tolist():
                    starts.append((x[k], int(self.map.cell_faces[near[k]])))
            log_amplitude = math.log(normalised[strong].max())
            if self._amplitude_prior is not None:
                log_amplitude = max(log_amplitude, self._amplitude_prior[0])
        z, h = d / noise, g / noise  # in noise sigmas
        fits = [self._fit_on_surface(p, f, x, z, h, log_amplitude) for p, f in starts]
        _, point, face, bary, log_amplitude, information = min(fits, key=lambda fit: fit[0])
        if self._learn_amplitude(log_amplitude, information) and learn_profile and width_learned:
            scale = h * math.exp(log_amplitude)
            offsets = x - point
            squared = np.einsum("ij,ij->i", offsets, offsets) / self.coupling_sigma**2  # in widths
            if self.coupling.add(squared, z / scale, scale * scale):
                self._use_profile()
        return point, face, bary, log_amplitude

    def _fit_on_surface(self, point, face, x, z, h, log_amplitude):
        """Levenberg-Marquardt of the coupling model from the surface point ``point`` on ``face`` and
        the log-amplitude ``log_amplitude`` (see :meth:`_refine`) to the crossings at ``x`` (k, 3) (mm)
        with deltas ``z`` and gains ``h`` both in units of each crossing's noise sigma (so the
        residuals are weighted already); returns (cost, point, face, bary, log amplitude, data
        information as its upper triangle ``(i00, i01, i02, i11, i12, i22)`` in ``(u0, u1, a)``).

        Within one tangent plane (rows ``t1, t2`` of the face frame) the finger is ``p_r + u0 t1 + u1 t2``,
        so ``|x_i - p|^2 = r2_i - 2 u.y_i + |u|^2`` with ``y_i = frame (x_i - p_r)`` (mm) and
        ``r2_i = |x_i - p_r|^2``, computed once per plane; ``d model_i / d u = 2 h_i exp(a) K'(q_i) (u - y_i)``
        with ``K'`` the profile's slope in squared distance. The 3 x 3 system is solved in plain floats
        (numpy's per-call overhead dominates on arrays of a few dozen crossings). A step that stays
        inside the face needs no projection: the point is on the surface and the fit ends in that plane."""
        profile = self.profile
        prior_u = 1.0 / self.pitch**2
        prior_mean_a, prior_a = 0.0, 0.0
        if self._amplitude_prior is not None:
            prior_mean_a, sigma_a = self._amplitude_prior
            prior_a = 1.0 / sigma_a**2
        start = point
        max_step = 0.5 * self.pitch
        columns = np.empty((len(z), 3))  # per plane: r2, -2 y0, -2 y1
        rows = np.empty((4, len(z)))  # J (d model / d (u0, u1, a)) and the residual

        def set_plane(point, face):
            """Fill the columns for the tangent plane at ``point`` on ``face``; returns its frame rows
            (t1, t2) and the offset (o0, o1) (mm) of ``point`` from the start, which the prior sees."""
            frame = self.projector.face_frames[face][:2]
            q = x - point
            columns[:, 0] = np.einsum("ij,ij->i", q, q)
            columns[:, 1:] = q @ (-2.0 * frame.T)
            return frame, ((point - start) @ frame.T).tolist()

        def evaluate(u0, u1, la):
            """(cost, residual, model, d model / d q), all but the cost in noise sigmas, at the
            in-plane offset (u0, u1) (mm) and log-amplitude ``la`` in the current plane."""
            k, slope = profile.at_squared(columns @ (1.0, u0, u1) + (u0 * u0 + u1 * u1))
            scale = h * math.exp(la)
            model = scale * k
            residual = z - model
            cost = (float(residual @ residual) + prior_u * ((o0 + u0) ** 2 + (o1 + u1) ** 2)
                    + prior_a * (la - prior_mean_a) ** 2)
            return cost, residual, model, scale * slope

        def normal_equations(model, residual, dmodel_dq, u0, u1):
            """Upper triangle of J^T J and J^T r at the in-plane offset (u0, u1) (mm), from one
            product of the rows [J; r] with themselves."""
            np.multiply(dmodel_dq, columns[:, 1] + 2.0 * u0, out=rows[0])
            np.multiply(dmodel_dq, columns[:, 2] + 2.0 * u1, out=rows[1])
            rows[2] = model
            rows[3] = residual
            (h00, h01, h02, b0), (_, h11, h12, b1), (_, _, h22, b2), _ = (rows @ rows.T).tolist()
            return (h00, h01, h02, h11, h12, h22), (b0, b1, b2)

        for _ in range(SURFACE_ROUNDS):
            # Levenberg-Marquardt in the tangent plane of the current face, then back onto the
            # surface on the side facing the same way; the next round starts in the new plane.
            frame, (o0, o1) = set_plane(point, face)
            u0 = u1 = 0.0
            cost, residual, model, dmodel_dq = evaluate(u0, u1, log_amplitude)
            damping = 1e-3
            for _ in range(FIT_ITERATIONS):
                (h00, h01, h02, h11, h12, h22), (b0, b1, b2) = normal_equations(model, residual, dmodel_dq, u0, u1)
                b0 -= prior_u * (o0 + u0)
                b1 -= prior_u * (o1 + u1)
                b2 -= prior_a * (log_amplitude - prior_mean_a)
                scale = 1.0 + damping
                h00, h11, h22 = (h00 + prior_u) * scale, (h11 + prior_u) * scale, (h22 + prior_a) * scale
                # Symmetric 3 x 3 solve by cofactors.
                c00, c01, c02 = h11 * h22 - h12 * h12, h02 * h12 - h01 * h22, h01 * h12 - h02 * h11
                determinant = h00 * c00 + h01 * c01 + h02 * c02
                if determinant == 0.0 or not math.isfinite(determinant):
                    break
                c11, c12, c22 = h00 * h22 - h02 * h02, h01 * h02 - h00 * h12, h00 * h11 - h01 * h01
                s0 = (c00 * b0 + c01 * b1 + c02 * b2) / determinant
                s1 = (c01 * b0 + c11 * b1 + c12 * b2) / determinant
                s2 = (c02 * b0 + c12 * b1 + c22 * b2) / determinant
                length = math.hypot(s0, s1)
                if length > max_step:
                    shrink = max_step / length
                    s0, s1, s2 = s0 * shrink, s1 * shrink, s2 * shrink
                trial = evaluate(u0 + s0, u1 + s1, log_amplitude + s2)
                if trial[0] <= cost:
                    u0, u1, log_amplitude = u0 + s0, u1 + s1, log_amplitude + s2
                    cost, residual, model, dmodel_dq = trial
                    damping = max(damping / 3.0, 1e-6)
                    if length < 0.05:
                        break
                else:
                    damping *= 4.0
            point = point + u0 * frame[0] + u1 * frame[1]
            bary = self.projector.barycentrics_in_face(point, face)
            if bary is not None:
                return cost, point, face, bary, log_amplitude, normal_equations(model, residual, dmodel_dq, u0, u1)[0]
            moved, faces, barys = self.projector.project(point, self.projector.face_normals[face])
            shift = math.dist(moved[0].tolist(), point.tolist())
            point, face, bary = moved[0], int(faces[0]), barys[0]
            if shift < 0.05:
                break
        _, (o0, o1) = set_plane(point, face)
        cost, residual, model, dmodel_dq = evaluate(0.0, 0.0, log_amplitude)
        return cost, point, face, bary, log_amplitude, normal_equations(model, residual, dmodel_dq, 0.0, 0.0)[0]

    def _learn_amplitude(self, log_amplitude: float, information: tuple[float, ...]) -> bool:
        """Keep the log-amplitude of fits whose tangential position the data alone pin within
        ``AMPLITUDE_WELL_POSED_MM`` (1 sigma); from ``AMPLITUDE_MIN_ESTIMATES`` on, their median and
        spread (1.4826 MAD, at least 0.05), updated every 10th estimate, are the amplitude prior of
        later fits. Returns whether the fit was well posed."""
        # Tangential 2 x 2 block of the inverse by cofactors, its largest eigenvalue in closed form.
        i00, i01, i02, i11, i12, i22 = information  # upper triangle, in (u0, u1, log amplitude)
        c00, c01, c11 = i11 * i22 - i12 * i12, i02 * i12 - i01 * i22, i00 * i22 - i02 * i02
        determinant = i00 * c00 + i01 * c01 + i02 * (i01 * i12 - i02 * i11)
        if determinant == 0.0 or not np.isfinite(determinant):
            return False
        v00, v01, v11 = c00 / determinant, c01 / determinant, c11 / determinant
        largest = 0.5 * (v00 + v11) + float(np.hypot(0.5 * (v00 - v11), v01))
        if not np.isfinite(largest) or largest > AMPLITUDE_WELL_POSED_MM**2:
            return False
        self._amplitude_estimates.append(float(log_amplitude))
        self._amplitude_count += 1
        if len(self._amplitude_estimates) >= AMPLITUDE_MIN_ESTIMATES and self._amplitude_count % 10 == 0:
            estimates = np.array(self._amplitude_estimates)
            centre = float(np.median(estimates))
            spread = max(1.4826 * float(np.median(np.abs(estimates - centre))), 0.05)
            self._amplitude_prior = (centre, spread)
        return True

    # ---- tracking

    def _track(self, touches: list[Touch], t: float) -> tuple[list[Touch], list[dict[str, Any]]]:
        previous_ids = list(self._tracks)
        assigned: dict[int, int] = {}
        if previous_ids and touches:
            before = np.array([self._tracks[i] for i in previous_ids])
            now = np.array([touch.point for touch in touches])
            cost = np.linalg.norm(before[:, None] - now[None], axis=2)
            gate = self.params.track_gate_mm
            rows, cols = linear_sum_assignment(np.where(cost <= gate, cost, 1e6))
            assigned = {int(c): previous_ids[r] for r, c in zip(rows, cols) if cost[r, c] <= gate}
        events: list[dict[str, Any]] = []
        tracked = []
        for j, touch in enumerate(touches):
            if j in assigned:
                touch = dataclasses.replace(touch, id=assigned[j])
                kind = "touch_move"
            else:
                touch = dataclasses.replace(touch, id=self._next_id)
                self._next_id += 1
                kind = "touch_down"
            tracked.append(touch)
            events.append({"type": kind, "t": round(t, 4), **touch.as_json()})
        live = {touch.id for touch in tracked}
        for track_id in previous_ids:
            if track_id not in live:
                events.append({"type": "touch_up", "t": round(t, 4), "id": track_id,
                               "point": [round(float(x), 3) for x in self._tracks[track_id]]})
        self._tracks = {touch.id: touch.point for touch in tracked}
        return tracked, events
