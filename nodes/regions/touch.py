"""``regions.touchable``: where a finger can touch the object from outside.

A finger is modelled as a ball of radius ``finger_radius_mm`` on a path that starts where a hand
fits and is at most ``finger_reach_mm`` long; a hand fits where a ball of radius ``hand_radius_mm``
can be brought in from far away. A surface point is touchable when the finger ball can touch it.
So a crease narrower than the fingertip, a slot, or the inside of a narrow-necked vase deeper than
a finger reaches is not touchable, while the inside of a bowl or a mug, where the hand goes in, is.
The table the object stands on comes in once the pose is known (:func:`clear_of_table`): the
fingertip stays above it, so the wedge between a round bottom and the table is not touchable.

The node works on the mesh before remeshing (so that it runs beside the remesh) and returns a
distance field; :func:`touchable_faces_of` reads any mesh of the same surface against it. On a
voxel grid of pitch ``h`` (at most ``finger_radius_mm / 4``, coarser only to keep the grid within
``MAX_VOXELS``), padded by ``hand_radius_mm + 2 h`` so that the grid's border is open space:

1. Surface voxels: those holding points sampled on every face at most ``h / 2`` apart, a
   26-connected shell, so the empty voxels outside it (6-connected to the border) are the outside.
2. Ball centres: outside voxels whose Euclidean distance to the nearest surface voxel is at least
   the ball's radius. Hand centres connected to the border bring the hand in; the open space is
   every voxel within ``hand_radius_mm`` of one.
3. Finger centres reached within ``finger_reach_mm`` of the open space: the shortest path through
   finger centres (26-neighbour steps of length ``h``, ``h sqrt 2``, ``h sqrt 3``; Dijkstra).
4. The field is the distance to the nearest reached finger centre. A face is touchable when the
   field at its centroid (trilinear) is at most ``finger_radius_mm + h sqrt 3``: the margin covers
   the surface voxels' and the centres' quantisation, so an open flat or convex surface is
   touchable everywhere. Widths and depths are resolved to about ``h``.

Lengths in millimetres; masks over faces.
"""
from __future__ import annotations

import heapq

import numba
import numpy as np
from pydantic import Field, model_validator

from ...graph.node import NodeParams, node
from ..data.types import Mesh, TouchField
from ..geometry.triangles import corners
from .faces import FaceGraph

MAX_VOXELS = 4_000_000
"""Largest grid (voxels) before the pitch grows past a quarter of the finger radius."""


class TouchParams(NodeParams):
    """The finger and hand sizes that decide what can be touched (mm)."""

    finger_radius_mm: float = Field(5.0, gt=0, le=20, description="radius of the fingertip ball")
    hand_radius_mm: float = Field(25.0, gt=0, le=100, description="radius of the ball a hand needs to come in")
    finger_reach_mm: float = Field(70.0, ge=0, le=200, description="longest finger path beyond where the hand fits")

    @model_validator(mode="after")
    def _hand_holds_finger(self) -> "TouchParams":
        if self.hand_radius_mm < self.finger_radius_mm:
            raise ValueError("hand_radius_mm must be at least finger_radius_mm")
        return self


def surface_points(vertices: np.ndarray, faces: np.ndarray, spacing: float) -> np.ndarray:
    """The vertices and, on every face with an edge longer than ``spacing`` mm, points on a barycentric
    lattice whose steps along each edge are at most ``spacing``: (P, 3)."""
    tri = corners(vertices, faces)
    longest = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)
    steps = np.ceil(longest / spacing).astype(np.int64)
    points = [vertices]
    for n in np.unique(steps[steps > 1]):
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = i + j <= n
        a, b = i[keep] / n, j[keep] / n
        bary = np.stack([1.0 - a - b, a, b], axis=1)  # (L, 3)
        points.append(np.einsum("lc,fcd->fld", bary, tri[steps == n]).reshape(-1, 3))
    return np.concatenate(points)


@numba.njit(cache=True)
def _path_lengths(free, seed, frontier, nx, ny, nz, pitch, limit):
    """Shortest path length (mm) from a ``seed`` voxel through ``free`` voxels (flat C-order masks of
    shape ``(nx, ny, nz)``), 26-neighbour steps; inf beyond ``limit``. Paths leave the seeds only
    through their ``frontier`` voxels (those next to a free voxel that is no seed)."""
    length = np.full(free.size, np.inf)
    steps = []
    for dx in range(-1, 2):
        for dy in range(-1, 2):
            for dz in range(-1, 2):
                if dx or dy or dz:
                    steps.append((dx, dy, dz, pitch * np.sqrt(float(dx * dx + dy * dy + dz * dz))))
    heap = [(0.0, 0)]
    heap.pop()
    for i in range(free.size):
        if seed[i]:
            length[i] = 0.0
            if frontier[i]:
                heap.append((0.0, i))
    heapq.heapify(heap)
    while heap:
        d, i = heapq.heappop(heap)
        if d > length[i]:
            continue
        x, rest = divmod(i, ny * nz)
        y, z = divmod(rest, nz)
        for dx, dy, dz, step in steps:
            u, v, w = x + dx, y + dy, z + dz
            if u < 0 or v < 0 or w < 0 or u >= nx or v >= ny or w >= nz:
                continue
            j = (u * ny + v) * nz + w
            candidate = d + step
            if free[j] and candidate <= limit and candidate < length[j]:
                length[j] = candidate
                heapq.heappush(heap, (candidate, j))
    return length


def touch_field(vertices: np.ndarray, faces: np.ndarray, params: TouchParams) -> TouchField:
    """The distance field to the finger centres that can be reached (module docstring), on the grid
    cropped to the mesh's bounding box plus the touch margin."""
    from scipy import ndimage

    finger, hand = params.finger_radius_mm, params.hand_radius_mm
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    pitch = finger / 4.0
    while True:
        pad = hand + 2.0 * pitch
        shape = tuple(int(v) for v in np.ceil((high - low + 2.0 * pad) / pitch) + 1)
        if np.prod(shape, dtype=np.float64) <= MAX_VOXELS:
            break
        pitch *= 1.25
    origin = low - pad
    surface = np.zeros(shape, dtype=bool)
    surface[tuple(np.rint((surface_points(vertices, faces, pitch / 2.0) - origin) / pitch).astype(np.int64).T)] = True
    labels, _ = ndimage.label(~surface)  # 6-connected
    outside = labels == labels[0, 0, 0]
    del labels
    to_surface = ndimage.distance_transform_edt(~surface, sampling=pitch)
    hand_centres = outside & (to_surface >= hand)
    labels, _ = ndimage.label(hand_centres)
    hand_centres = labels == labels[0, 0, 0]
    del labels
    open_space = ndimage.distance_transform_edt(~hand_centres, sampling=pitch) <= hand
    free = outside & (to_surface >= finger)
    del to_surface, hand_centres, outside
    seed = free & open_space
    frontier = seed & ndimage.binary_dilation(free & ~seed, structure=np.ones((3, 3, 3), dtype=bool))
    lengths = _path_lengths(free.ravel(), seed.ravel(), frontier.ravel(), *shape, pitch, params.finger_reach_mm)
    reached = free & np.isfinite(lengths.reshape(shape))  # the grid's border at least: it is open space
    margin = int(np.ceil(finger / pitch)) + 3  # the grid around the surface, where centroids are read
    crop = tuple(slice(int(np.floor((lo - origin_k) / pitch)) - margin, int(np.ceil((hi - origin_k) / pitch)) + margin + 1)
                 for lo, hi, origin_k in zip(low, high, origin))
    distance = ndimage.distance_transform_edt(~reached, sampling=pitch)[crop].astype(np.float32)
    return TouchField(origin=origin + pitch * np.array([c.start for c in crop]), pitch_mm=float(pitch), distance_mm=distance,
                      finger_radius_mm=finger, hand_radius_mm=hand, finger_reach_mm=params.finger_reach_mm)


def touchable_faces_of(field: TouchField, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m,) bool: the faces whose centroid the finger ball touches (module docstring, step 4)."""
    from scipy import ndimage

    centroids = corners(vertices, faces).mean(axis=1)
    at = ndimage.map_coordinates(field.distance_mm, ((centroids - field.origin) / field.pitch_mm).T, order=1, cval=np.inf)
    return at <= field.finger_radius_mm + field.pitch_mm * np.sqrt(3.0)


def clear_of_table(vertices: np.ndarray, faces: np.ndarray, face_normals: np.ndarray, down: np.ndarray,
                   finger_radius_mm: float) -> np.ndarray:
    """(m,) bool: the faces a fingertip ball above the support plane can touch along their unit normal
    ``n`` (``face_normals``): the ball's centre ``c + r n`` (``c`` the centroid) at least ``r`` above
    the plane, i.e. the centroid's height ``h >= r (1 + n . down)`` (``down`` as in :mod:`.detect`;
    the plane touches the lowest vertex). On a ball of radius ``R`` resting on the table this leaves out the cap within
    ``arccos((R - r) / (R + r))`` of the contact, where a fingertip on the table meets it."""
    height = float((vertices @ down).max()) - corners(vertices, faces).mean(axis=1) @ down
    return height >= finger_radius_mm * (1.0 + face_normals @ down)


def pocket_of(graph: FaceGraph, around: np.ndarray, untouchable: np.ndarray, blocked: np.ndarray) -> np.ndarray:
    """The ``untouchable`` faces edge-connected to the faces ``around`` through untouchable faces (a
    vessel's inside beyond a finger's reach around a Tx pole at its bottom), unless they reach a
    ``blocked`` face (the base and its exclusion: the traces' way out)."""
    labels = graph.components(untouchable | around)
    near_blocked, _ = graph.vertex_masks(blocked)
    reaching = labels[near_blocked[graph.faces].any(axis=1) & (labels >= 0)]
    return untouchable & np.isin(labels, np.setdiff1d(labels[around], reaching))


def touch_summary(field: TouchField, share: float) -> dict:
    """The finger model and the touchable share of the surface, as metrics.json reports them."""
    return {"finger_radius_mm": field.finger_radius_mm, "hand_radius_mm": field.hand_radius_mm,
            "finger_reach_mm": field.finger_reach_mm, "pitch_mm": field.pitch_mm, "share": share}


@node("regions.touchable", params=TouchParams, inputs=("mesh",), outputs=("touchable",))
def touchable_surface(params: TouchParams, mesh: Mesh) -> TouchField:
    """Where a finger can touch from outside, as a distance field (module docstring)."""
    return touch_field(np.ascontiguousarray(mesh.vertices, dtype=np.float64),
                       np.ascontiguousarray(mesh.faces, dtype=np.int64), params)
