"""Mesh clean-up and isotropic remeshing with pymeshlab (the paper's MeshLab step).

Nodes:

* ``mesh.repair`` -- remove duplicate vertices/faces, null faces and unreferenced vertices, repair
  non-manifold edges and vertices (the copies a pinch vertex is split into are moved apart, so
  remeshing does not weld them again), orient faces coherently, close holes (every hole by default, so a
  scan's open bottom is closed), keep only the largest
  connected component (a scan's loose fragments), and make the orientation outward (signed
  volume > 0). A surface these filters cannot make manifold and coherently oriented (a model whose
  parts were glued through each other, a non-orientable export) is rebuilt by screened Poisson from
  points sampled evenly on all its parts (:func:`.reconstruct.rebuilt_from_samples`), then cleaned again. Each change
  is listed in ``Mesh.repairs``.
* ``mesh.remesh`` -- isotropic explicit remeshing to a target edge length in mm, or to a target
  vertex count (the edge length is solved for in a few passes). A dense input (a scan with
  millions of faces) is decimated first; a vertex count that misses its target is logged and listed.
"""
from __future__ import annotations

import dataclasses
import logging
import math
from typing import Literal

import numpy as np
import pymeshlab
from pydantic import Field, model_validator

from ...graph.errors import UserError
from ...graph.node import NodeParams, node
from ..data.types import Mesh
from ..geometry.triangles import areas, corners, cross_products, signed_volume
from .meshset import face_components, from_meshset, to_meshset
from .reconstruct import one_sided, rebuilt_from_samples
from .topology import keeps_closed_topology

log = logging.getLogger(__name__)

DECIMATE_ABOVE = 8
"""mesh.remesh decimates an input with more than this many times the target's faces ..."""
DECIMATE_TO = 2
"""... to this many times the target's faces (quadric edge collapse), before remeshing."""
TARGET_TOLERANCE = 0.10
"""mesh.remesh: a vertex count within this share of the target is on target."""
MAX_REMESH_VERTICES = 1_000_000
"""mesh.remesh: the largest mesh it makes (the layout's memory grows with it: 1.4 GB at 100,000 vertices)."""
SPLIT_SEPARATION = 0.2
"""mesh.repair: each copy of a split non-manifold vertex moves this share of the way to the centroid
of its own neighbours."""
NON_MANIFOLD_ROUNDS = 4
"""mesh.repair: rounds of non-manifold edge and vertex repair before the surface is rebuilt instead."""
FLAT_FACE_RATIO = 100.0
"""mesh.remesh: a face whose longest edge is more than this many times its height is nearly flat (the
remesher can leave three vertices in a line at a crease; a regular remesh stays below 30); an edge
flip removes it."""


def keep_largest_component(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, str | None]:
    """The connected component with the largest surface area, unreferenced vertices dropped, and
    a line saying what was dropped (None when there was one component)."""
    count, labels = face_components(faces, len(vertices))
    dropped = None
    if count > 1:
        face_areas = areas(corners(vertices, faces))
        per_label = np.bincount(labels, weights=face_areas)
        keep = int(np.argmax(per_label))
        dropped = (
            f"dropped {count - 1} loose fragment(s) ({int((labels != keep).sum()):,} faces, "
            f"{100 * (1 - per_label[keep] / per_label.sum()):.1f}% of the area), kept the largest component"
        )
        faces = faces[labels == keep]
    used = np.unique(faces)
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return np.ascontiguousarray(vertices[used]), np.ascontiguousarray(remap[faces]), dropped


class RepairParams(NodeParams):
    """Which clean-up steps run."""

    close_holes: bool = Field(True, description="fill holes bounded by at most max_hole_edges edges")
    max_hole_edges: int | None = Field(
        None, ge=3, description="largest hole (in boundary edges) to close; null: every hole (a scan's open bottom)"
    )
    keep_largest: bool = Field(True, description="drop every component but the largest (by area)")
    non_manifold_edges: Literal["remove_faces", "split_vertices"] = Field(
        "remove_faces", description="how non-manifold edges are repaired"
    )
    rebuild_depth: int = Field(7, ge=5, le=10, description="a surface repair cannot make manifold and coherently "
                               "oriented is rebuilt from samples by screened Poisson at this octree depth")


def separate_coincident(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, int]:
    """``vertices`` with every vertex that shares its position with another (after duplicates are
    merged: the copies of a split non-manifold vertex) moved ``SPLIT_SEPARATION`` of the way to the
    centroid of its neighbours, and how many moved."""
    _, inverse, counts = np.unique(vertices, axis=0, return_inverse=True, return_counts=True)
    shared = counts[inverse.ravel()] > 1
    if not shared.any():
        return vertices, 0
    halfedges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    halfedges = halfedges[shared[halfedges[:, 0]]]
    sums = np.zeros_like(vertices)
    np.add.at(sums, halfedges[:, 0], vertices[halfedges[:, 1]])
    degree = np.bincount(halfedges[:, 0], minlength=len(vertices))
    moved = vertices.copy()
    index = np.flatnonzero(shared)
    moved[index] += SPLIT_SEPARATION * (sums[index] / degree[index, None] - vertices[index])
    return moved, len(index)


def counted(meshset: pymeshlab.MeshSet) -> tuple[int, int]:
    """``(vertices, faces)`` of the current mesh."""
    return meshset.current_mesh().vertex_number(), meshset.current_mesh().face_number()


def clean(meshset: pymeshlab.MeshSet, params: RepairParams) -> tuple[list[str], str | None]:
    """Run the pymeshlab clean-up filters on ``meshset``: one line per change they made, and what
    non-manifold edges and vertices they left (None: none)."""
    done = []
    before = counted(meshset)
    meshset.meshing_remove_duplicate_vertices()
    meshset.meshing_remove_duplicate_faces()
    meshset.meshing_remove_null_faces()
    meshset.meshing_remove_unreferenced_vertices()
    after = counted(meshset)
    if after != before:
        done.append(f"merged or removed {before[0] - after[0]:,} duplicate/unused vertices and "
                    f"{before[1] - after[1]:,} duplicate/degenerate faces")
    repaired = after
    measures = meshset.get_topological_measures()  # a filter costs seconds on a dense scan: only the needed ones run
    if measures["non_two_manifold_edges"] or measures["non_two_manifold_vertices"]:
        method = "Remove Faces" if params.non_manifold_edges == "remove_faces" else "Split Vertices"
        for _ in range(NON_MANIFOLD_ROUNDS):  # a round's removals and splits can leave new non-manifold vertices
            meshset.meshing_repair_non_manifold_edges(method=method)
            meshset.meshing_repair_non_manifold_vertices()
            meshset.meshing_remove_unreferenced_vertices()
            measures = meshset.get_topological_measures()
            if not (measures["non_two_manifold_edges"] or measures["non_two_manifold_vertices"]):
                break
        repaired = counted(meshset)
        if repaired != after:
            done.append(f"repaired non-manifold edges/vertices (vertices {after[0]:,} -> {repaired[0]:,}, "
                        f"faces {after[1]:,} -> {repaired[1]:,})")
    meshset.meshing_re_orient_faces_coherently()
    non_manifold = ", ".join(f"{measures[key]:,} {name}" for key, name in (("non_two_manifold_edges", "non-manifold edges"),
                                                                    ("non_two_manifold_vertices", "non-manifold vertices"))
                             if measures[key]) or None
    if params.close_holes and measures["boundary_edges"] and non_manifold is None:  # else the surface is rebuilt (repair_mesh)
        holes = measures["number_holes"]
        largest = params.max_hole_edges or 3 * counted(meshset)[1] + 3  # a hole has fewer edges than 3 x faces
        try:
            meshset.meshing_close_holes(maxholesize=largest)
            left = crossing = meshset.get_topological_measures()["boundary_edges"]
            if left:  # a patch free of self-intersections was not found (a scan's wide, warped open bottom)
                meshset.meshing_close_holes(maxholesize=largest, selfintersection=False)
                crossing = left - meshset.get_topological_measures()["boundary_edges"]
        except pymeshlab.PyMeshLabException as exc:
            raise UserError(
                f"closing holes failed ({str(exc).strip()[:100]}): set close_holes: false and "
                "fill the holes in a mesh editor"
            ) from None
        filled = counted(meshset)[1] - repaired[1]
        if filled:
            done.append(f"closed {max(holes, 1)} hole(s) with {filled:,} faces"
                        + (f" ({crossing:,} of their boundary edges closed by a patch that may cross the surface)"
                           if crossing else ""))
    return done, non_manifold


@node("mesh.repair", params=RepairParams, inputs=("mesh",), outputs=("mesh",))
def repair_mesh(params: RepairParams, mesh: Mesh) -> Mesh:
    """Clean a scanned mesh with pymeshlab and orient it outward (signed volume > 0); when the clean-up
    leaves it non-manifold or one-sided, the input is rebuilt from samples of all its parts instead and
    cleaned again; every change is appended to ``Mesh.repairs``."""
    vertices, faces, done, broken = cleaned(mesh.vertices, mesh.faces, params, mesh.source)
    if broken:  # every part of the input sampled: parts glued through each other merge into one surface
        vertices, faces, rebuilt = rebuilt_from_samples(mesh.vertices, mesh.faces, params.rebuild_depth, mesh.source_name,
                                                        broken)
        vertices, faces, again, _ = cleaned(vertices, faces, params, mesh.source)
        done = [rebuilt, *again]
    if signed_volume(vertices, faces) < 0.0:
        faces = np.ascontiguousarray(faces[:, ::-1])
        done.append("flipped the faces to point outward")
    return dataclasses.replace(mesh, vertices=vertices, faces=faces, repairs=mesh.repairs + tuple(done))


def cleaned(vertices: np.ndarray, faces: np.ndarray, params: RepairParams, source: str
            ) -> tuple[np.ndarray, np.ndarray, list[str], str | None]:
    """:func:`clean`, split non-manifold vertices moved apart and the largest component kept: ``(vertices,
    faces, one line per change, what keeps the result from being a manifold, coherently oriented
    surface or None)``."""
    meshset = to_meshset(vertices, faces)
    done, non_manifold = clean(meshset, params)
    vertices, faces = from_meshset(meshset)
    vertices, separated = separate_coincident(vertices, faces)
    if separated:
        done.append(f"moved apart the {separated} copies of split non-manifold vertices, so remeshing keeps them apart")
    if params.keep_largest and len(faces):
        vertices, faces, dropped = keep_largest_component(vertices, faces)
        done += [dropped] if dropped else []
    if len(faces) == 0:
        raise UserError(f"repair left no faces in {source}: the input is not a usable surface")
    return vertices, faces, done, non_manifold or one_sided(faces)


class RemeshParams(NodeParams):
    """Set exactly one of ``target_edge_mm`` and ``target_vertices``."""

    target_edge_mm: float | None = Field(None, gt=0, description="target edge length (mm)")
    target_vertices: int | None = Field(
        None, ge=100, le=MAX_REMESH_VERTICES, description="target vertex count (within ~10%)"
    )
    iterations: int = Field(10, ge=1, le=50, description="remeshing iterations per pass")
    feature_angle_deg: float = Field(30.0, gt=0, lt=180, description="crease angle kept sharp (deg)")
    max_passes: int = Field(3, ge=1, le=6, description="passes to hit target_vertices")

    @model_validator(mode="after")
    def _exactly_one_target(self) -> "RemeshParams":
        if (self.target_edge_mm is None) == (self.target_vertices is None):
            raise ValueError("set exactly one of target_edge_mm and target_vertices")
        return self


def edge_length_for_vertices(area_mm2: float, vertex_count: int) -> float:
    """Edge length (mm) of an equilateral closed mesh with ``vertex_count`` vertices and given area.

    A closed mesh has about ``2 V`` faces of area ``sqrt(3)/4 L^2`` each.
    """
    return math.sqrt(4.0 * area_mm2 / (math.sqrt(3.0) * 2.0 * vertex_count))


def isotropic_remesh(
    vertices: np.ndarray, faces: np.ndarray, edge_mm: float, iterations: int, feature_angle_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """One pymeshlab isotropic explicit remeshing run at absolute edge length ``edge_mm``. Every vertex
    is reprojected onto the input surface, so the remesher's per-operation surface-distance check is
    off (it only cost time)."""
    meshset = to_meshset(vertices, faces)
    meshset.meshing_isotropic_explicit_remeshing(
        iterations=iterations,
        targetlen=pymeshlab.PureValue(edge_mm),
        featuredeg=feature_angle_deg,
        adaptive=False,
        checksurfdist=False,
    )
    return from_meshset(meshset)


def decimate_dense(
    vertices: np.ndarray, faces: np.ndarray, target_faces: int
) -> tuple[np.ndarray, np.ndarray, str | None]:
    """A mesh with more than ``DECIMATE_ABOVE x target_faces`` faces decimated to ``DECIMATE_TO x
    target_faces`` by quadric edge collapse, and a line saying so.

    First fast-simplification's collapse (a dense scan's millions of faces in seconds); its result is
    kept when it is one closed, manifold, coherently oriented component whose Euler characteristic is
    the input's as a closed mesh (``V - F / 2``: a repaired input is closed), so the decimation changed
    no topology. Otherwise pymeshlab's collapse, which keeps the topology by construction but is slower."""
    if len(faces) <= DECIMATE_ABOVE * target_faces:
        return vertices, faces, None
    import fast_simplification  # imported when a dense input needs it

    goal = int(DECIMATE_TO * target_faces)
    # writable C-ordered copies: the binding takes no read-only (cached, memory-mapped) arrays
    fast_vertices, fast_faces = fast_simplification.simplify(np.array(vertices, dtype=np.float64, order="C"),
                                                             np.array(faces, dtype=np.int64, order="C"), target_count=goal)
    fast_faces = np.asarray(fast_faces, dtype=np.int64)
    if keeps_closed_topology(vertices, faces, fast_vertices, fast_faces):
        note = f"decimated a dense input from {len(faces):,} to {len(fast_faces):,} faces before remeshing"
        return np.ascontiguousarray(fast_vertices, dtype=np.float64), fast_faces, note
    meshset = to_meshset(vertices, faces)
    meshset.meshing_decimation_quadric_edge_collapse(targetfacenum=goal, preservetopology=True, planarquadric=True)
    decimated_vertices, decimated_faces = from_meshset(meshset)
    note = (f"decimated a dense input from {len(faces):,} to {len(decimated_faces):,} faces before remeshing "
            "(the topology-keeping collapse: the fast one changed the surface's topology)")
    return decimated_vertices, decimated_faces, note


def remesh_to_count(
    vertices: np.ndarray, faces: np.ndarray, params: RemeshParams
) -> tuple[np.ndarray, np.ndarray, str | None]:
    """Remesh to about ``params.target_vertices``: the equilateral edge estimate, corrected by
    ``sqrt(V_got / V_target)`` until within ``TARGET_TOLERANCE`` (at most ``max_passes``).

    A noisy scan is full of dihedral angles above ``feature_angle_deg`` that the remesher keeps as
    creases and will not collapse, so it stays far above the target: after a pass that lands above
    it by more than the tolerance, the remaining passes keep no creases (the returned line says so).
    """
    target = params.target_vertices
    edge = edge_length_for_vertices(float(areas(corners(vertices, faces)).sum()), target)
    feature_angle, first_count = params.feature_angle_deg, None
    best: tuple[float, np.ndarray, np.ndarray, float] | None = None
    for _ in range(params.max_passes):
        got_vertices, got_faces = isotropic_remesh(vertices, faces, edge, params.iterations, feature_angle)
        error = abs(len(got_vertices) - target) / target
        if best is None or error < best[0]:
            best = (error, got_vertices, got_faces, feature_angle)
        if error <= TARGET_TOLERANCE:
            break
        if len(got_vertices) > target and feature_angle < 180.0:
            feature_angle, first_count = 180.0, len(got_vertices)
        else:
            edge *= math.sqrt(len(got_vertices) / target)
    _, got_vertices, got_faces, used_angle = best
    note = None
    if used_angle != params.feature_angle_deg:
        note = (f"kept no creases: with creases over {params.feature_angle_deg:g} deg kept, remeshing gave "
                f"{first_count:,} vertices for {target:,} (a noisy surface)")
    return got_vertices, got_faces, note


def flat_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Mask of the faces whose longest edge is more than :data:`FLAT_FACE_RATIO` times their height."""
    points = corners(vertices, faces)
    longest = np.max(np.linalg.norm(points - np.roll(points, 1, axis=1), axis=2), axis=1)
    return longest * longest > FLAT_FACE_RATIO * np.linalg.norm(cross_products(points), axis=1)


def remove_flat_faces(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """``(vertices, faces, count)``: the :func:`flat_faces` that pymeshlab's edge flips remove (a vertex
    lying on its face's opposite edge) removed, and how many; the mesh unchanged when it has none, or
    when the flips would change its topology. Flat faces left (two vertices at one point) are no
    error here: the topology check refuses those of zero area."""
    count = int(np.count_nonzero(flat_faces(vertices, faces)))
    if not count:
        return vertices, faces, 0
    meshset = to_meshset(vertices, faces)
    meshset.meshing_remove_t_vertices(method="Edge Flip", threshold=FLAT_FACE_RATIO, repeat=True)
    flipped_vertices, flipped_faces = from_meshset(meshset)
    if not keeps_closed_topology(vertices, faces, flipped_vertices, flipped_faces):
        return vertices, faces, 0
    return flipped_vertices, flipped_faces, count - int(np.count_nonzero(flat_faces(flipped_vertices, flipped_faces)))


@node("mesh.remesh", params=RemeshParams, inputs=("mesh",), outputs=("mesh",))
def remesh(params: RemeshParams, mesh: Mesh) -> Mesh:
    """Isotropic remeshing to ``target_edge_mm``, or to about ``target_vertices`` vertices (a dense
    input decimated first, a missed vertex target logged; both listed in ``Mesh.repairs``)."""
    if params.target_vertices is not None:
        target_faces = 2 * params.target_vertices
    else:
        area = float(areas(corners(mesh.vertices, mesh.faces)).sum())
        target_faces = max(1, int(area / (math.sqrt(3.0) / 4.0 * params.target_edge_mm**2)))
        if target_faces > 2 * MAX_REMESH_VERTICES:
            raise UserError(
                f"target_edge_mm {params.target_edge_mm:g} would remesh the {area:,.0f} mm2 surface into about "
                f"{target_faces // 2:,} vertices (at most {MAX_REMESH_VERTICES:,}): raise target_edge_mm to at least "
                f"{edge_length_for_vertices(area, MAX_REMESH_VERTICES):.2g}"
            )
    vertices, faces, note = decimate_dense(mesh.vertices, mesh.faces, target_faces)
    done = [note] if note else []
    if params.target_edge_mm is not None:
        vertices, faces = isotropic_remesh(
            vertices, faces, params.target_edge_mm, params.iterations, params.feature_angle_deg
        )
    else:
        vertices, faces, creases = remesh_to_count(vertices, faces, params)
        done += [creases] if creases else []
        miss = abs(len(vertices) - params.target_vertices) / params.target_vertices
        if miss > TARGET_TOLERANCE:
            line = (f"remeshing missed its target: {len(vertices):,} vertices for {params.target_vertices:,} "
                    f"({100 * miss:.0f}% off)")
            log.warning("mesh.remesh: %s", line)
            done.append(line)
    vertices, faces, flat = remove_flat_faces(vertices, faces)
    if flat:
        done.append(f"removed {flat:,} nearly flat face(s) the remesher left, by edge flips")
    if signed_volume(vertices, faces) * signed_volume(mesh.vertices, mesh.faces) < 0.0:
        faces = np.ascontiguousarray(faces[:, ::-1])
    return dataclasses.replace(mesh, vertices=vertices, faces=faces, repairs=mesh.repairs + tuple(done))
