"""Surface reconstruction of a scan that comes as a point cloud (no faces): pymeshlab's screened
Poisson reconstruction, which returns a closed (watertight) surface and so also fills the scan's
holes. Loose fragments become small separate components that ``mesh.repair`` drops.

Normals estimated from a noisy cloud flip here and there, and the octree's finest cells then close
small spurious handles through the surface, which a coarser octree does not. When the surface has a
handle, the reconstruction is tried again with the normals the file brings, if any (second, not
first: a tool may have left them unoriented, and on clouds the estimate handles they give another
surface), then with estimated normals one depth coarser at a time down to ``MIN_DEPTH``; the first
genus-0 surface is kept. A real handle (a mug's) stays at every try, and the last goes on to the
topology check, which refuses it in one line.

The same reconstruction rebuilds a mesh ``mesh.repair`` cannot make manifold and coherently oriented,
from points sampled on it (:func:`rebuilt_from_samples`)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pymeshlab
import trimesh
from scipy.spatial import cKDTree

from ...graph.errors import UserError
from ..geometry.triangles import areas, corners, random_barycentrics
from .topology import inconsistent_edges, topology_report

MIN_POINTS = 100
"""Fewer points than this cannot describe a surface."""
NORMAL_NEIGHBOURS = 12
"""Neighbours per point for the normal estimate."""
STRAY_SPACING_FACTOR = 10.0
"""A point whose mean distance to its ``NORMAL_NEIGHBOURS`` nearest neighbours is more than this many
times the cloud's median is a stray (a reflection, dust, a point of the room): dropped before the
reconstruction, whose octree would otherwise span it and lose resolution on the object."""
MIN_DEPTH = 5
"""The coarsest octree depth a noisy cloud is reconstructed at (32 cells along the longest side)."""
REBUILD_CHECKED_VERTICES = 20_000
"""Vertices of a surface rebuilt from samples of a broken mesh measured against it."""
POINTS_PER_DEPTH_CELL = 24
"""A cloud keeps at most ``POINTS_PER_DEPTH_CELL * 4**depth`` points: about four per cell of the
octree's finest level that a closed surface meets (some ``6 * 4**depth``). More points add nothing
the grid can resolve, and the normal estimate's time grows with them."""


def stray_points(points: np.ndarray) -> np.ndarray:
    """Mask of the points (n, 3) farther from their neighbours than :data:`STRAY_SPACING_FACTOR` times
    the cloud's median spacing (mean distance to the ``NORMAL_NEIGHBOURS`` nearest)."""
    neighbours = min(NORMAL_NEIGHBOURS, len(points) - 1)
    distances, _ = cKDTree(points).query(points, k=neighbours + 1)
    spacing = distances[:, 1:].mean(axis=1)
    return spacing > STRAY_SPACING_FACTOR * np.median(spacing)


@dataclasses.dataclass(frozen=True)
class Reconstruction:
    """A closed surface through a point cloud: ``vertices`` / ``faces``, the ``stride`` the cloud was
    thinned by (1: every point used), the ``strays`` dropped, the octree ``depth`` and the
    ``normals`` ("the file's normals" or "estimated normals") kept, and the ``handles`` (genus) of
    the surface of each try before (by its depth and normals)."""

    vertices: np.ndarray
    faces: np.ndarray
    stride: int
    strays: int
    depth: int
    normals: str
    handles: dict[str, int]


def reconstruct_from_points(points: np.ndarray, depth: int, name: str,
                            normals: np.ndarray | None = None) -> Reconstruction:
    """The screened Poisson surface through ``points`` (n, 3) read from the file ``name`` (for
    messages), with the file's unit ``normals`` (n, 3) if given, at octree ``depth`` or coarser
    (module docstring).

    A cloud denser than ``POINTS_PER_DEPTH_CELL * 4**depth`` is thinned to every ``stride``-th point
    (1: all of them), then its ``strays`` (:func:`stray_points`) are dropped. Estimated normals come
    from ``NORMAL_NEIGHBOURS`` neighbours; ``depth`` is the octree depth (grid of ``2**depth`` cells
    along the longest side). One thread: deterministic, and faster on a loaded machine than many.
    """
    if len(points) < MIN_POINTS:
        raise UserError(
            f"{name} holds {len(points)} point{'' if len(points) == 1 else 's'} and no faces: a scan needs at "
            f"least {MIN_POINTS} points to be reconstructed, export the scan with more points or as a mesh"
        )
    stride = -(-len(points) // (POINTS_PER_DEPTH_CELL * 4**depth))
    stray = stray_points(points[::stride])
    kept = points[::stride][~stray]
    given = None if normals is None else normals[::stride][~stray]
    tries = [(depth, None)] + ([(depth, given)] if given is not None else [])
    tries += [(d, None) for d in range(depth - 1, MIN_DEPTH - 1, -1)]
    attempts: list[tuple[str, int]] = []  # (depth and normals, genus) of each try so far
    for tried, try_normals in tries:
        vertices, faces = _screened_poisson(kept, tried, try_normals)
        if len(faces) == 0:
            raise UserError(
                f"screened Poisson found no surface in the {len(points)} points of {name}: the points do not "
                "sample a closed object; export the scan as a mesh"
            )
        source = "estimated normals" if try_normals is None else "the file's normals"
        genus = int(topology_report(vertices, faces)["genus"])  # over every component; holes do not count
        attempts.append((f"depth {tried} with {source}", genus))
        if genus == 0:
            break
    return Reconstruction(vertices, faces, stride, int(np.count_nonzero(stray)), tried, source, dict(attempts[:-1]))


def _screened_poisson(points: np.ndarray, depth: int, normals: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    meshset = pymeshlab.MeshSet()
    if normals is None:
        meshset.add_mesh(pymeshlab.Mesh(vertex_matrix=np.ascontiguousarray(points, dtype=np.float64)))
        meshset.compute_normal_for_point_clouds(k=NORMAL_NEIGHBOURS, smoothiter=2)
    else:
        meshset.add_mesh(pymeshlab.Mesh(vertex_matrix=np.ascontiguousarray(points, dtype=np.float64),
                                        v_normals_matrix=np.ascontiguousarray(normals, dtype=np.float64)))
    meshset.generate_surface_reconstruction_screened_poisson(depth=depth, threads=1)
    current = meshset.current_mesh()
    return (np.ascontiguousarray(current.vertex_matrix(), dtype=np.float64),
            np.ascontiguousarray(current.face_matrix(), dtype=np.int64))


def one_sided(faces: np.ndarray) -> str | None:
    """What :func:`.topology.inconsistent_edges` finds in ``faces``, in words, or None when none."""
    count = inconsistent_edges(faces)
    return f"{count:,} edges whose faces cannot be oriented alike" if count else None


def rebuilt_from_samples(vertices: np.ndarray, faces: np.ndarray, depth: int, name: str, broken: str
                         ) -> tuple[np.ndarray, np.ndarray, str]:
    """The surface screened Poisson reconstructs (:func:`reconstruct_from_points`, normals
    estimated) from ``POINTS_PER_DEPTH_CELL * 4**depth`` points spread over ``faces`` by area (fixed
    seed; faces of zero area get none), and the repair line naming ``broken``, what made it necessary.
    ``UserError`` when nine in ten of its vertices (up to ``REBUILD_CHECKED_VERTICES`` of them) are not
    within one cell of the Poisson grid of the input: sheets without thickness rebuild into a blob."""
    face_areas = areas(corners(vertices, faces))
    rng = np.random.default_rng(0)
    count = POINTS_PER_DEPTH_CELL * 4**depth
    picked = rng.choice(len(faces), count, p=face_areas / face_areas.sum())
    points = np.einsum("kc,kcd->kd", random_barycentrics(rng, count), vertices[faces[picked]])
    surface = reconstruct_from_points(points, depth, f"the surface of {name}")
    cell = float(np.ptp(points, axis=0).max()) / 2**surface.depth
    checked = surface.vertices[:: -(-len(surface.vertices) // REBUILD_CHECKED_VERTICES)]
    off = float(np.percentile(trimesh.Trimesh(vertices, faces, process=False).nearest.on_surface(checked)[1], 90))
    if off > cell:
        raise UserError(
            f"{name}: repair left {broken}, and the surface rebuilt from samples of it strays {off:.1f} mm from it (90th "
            f"percentile, more than the {cell:.1f} mm grid): it is no solid's surface (sheets without thickness, open "
            "parts); make it one closed, manifold surface in a mesh editor, or export the parts as one solid")
    line = (f"rebuilt the surface from {count:,} points sampled on it (screened Poisson, depth {surface.depth}, within "
            f"{off:.1f} mm of it at nine vertices in ten): repair left {broken}; {len(surface.faces):,} faces")
    return surface.vertices, surface.faces, line
