"""Mesh ingest: read a mesh file (or the embedded bunny) and scale it to a physical size in mm.

Nodes:

* ``mesh.load``  -- OBJ/PLY/STL/OFF/GLB via trimesh (a GLB scene is flattened into one mesh), or
  ``builtin:bunny`` (pymeshlab's bundled Stanford bunny). A point cloud (a PLY or XYZ file with
  points and no faces) is reconstructed into a closed surface (:mod:`.reconstruct`), listed in
  ``Mesh.repairs``. The declared ``units`` convert the file's
  numbers to millimetres; ``unitless`` keeps them as they are (follow with ``mesh.scale``).
  ``Mesh.source`` is ``"<path> sha256:<hex of the file bytes>"``; ``Params.input_files()`` names
  the file so the engine keys the cache on its content.
* ``mesh.scale`` -- uniform scaling to a physical size: a unit factor, a bounding-box diagonal or a
  longest bounding-box extent, about the origin (default) or the bounding-box centre.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Literal

import numpy as np
import trimesh
from pydantic import Field, model_validator

from ...graph.errors import UserError
from ...graph.hashing import file_sha256
from ...graph.node import NodeParams, node
from ..data.builtin import builtin_mesh_path
from ..data.types import Mesh
from .reconstruct import reconstruct_from_points
from .topology import RECONSTRUCTED

MM_PER_UNIT = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4, "unitless": 1.0}
"""Millimetres per declared unit (``unitless`` keeps the numbers; scale afterwards)."""
OBJECT_DIAGONAL_RANGE_MM = (10.0, 10_000.0)
"""Bounding-box diagonals (mm) of objects the method can cover: below, a pad and its trace do not fit;
above, it is no object a person sets on a table (and the per-object arrays outgrow the machine)."""

SUPPORTED_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf", ".xyz")
GLTF_SUFFIXES = (".glb", ".gltf")
"""glTF files, whose numbers are metres by the format's definition (phone scanning apps export them)."""


def resolve_mesh_path(path: str) -> Path:
    """The file behind ``path``: a ``builtin:`` name resolves inside the installed pymeshlab."""
    if path.startswith("builtin:"):
        return builtin_mesh_path(path)
    return Path(path).expanduser()


class LoadParams(NodeParams):
    """Where the mesh comes from and what unit its numbers are in."""

    path: str = Field(
        "builtin:bunny", description="mesh file (OBJ/PLY/STL/OFF/GLB), point cloud (PLY/XYZ) or builtin:bunny"
    )
    units: Literal["mm", "cm", "m", "in", "unitless"] = Field(
        "unitless", description="unit of the file's coordinates; unitless = keep numbers, scale later"
    )
    poisson_depth: int = Field(7, ge=5, le=10, description="point clouds: screened Poisson octree depth")

    def input_files(self) -> list[str]:
        return [str(resolve_mesh_path(self.path))]


def read_geometry(path: Path, fix: str) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(vertices, faces, normals)`` as trimesh reads them (scenes flattened; a point cloud has no
    faces, and its :func:`scan_normals` or None; a mesh's normals are None)."""
    try:
        loaded = trimesh.load(str(path), process=False)
        if isinstance(loaded, trimesh.PointCloud):
            return (np.asarray(loaded.vertices, dtype=np.float64), np.zeros((0, 3), dtype=np.int64),
                    scan_normals(path, loaded))
        if not isinstance(loaded, trimesh.Trimesh):
            loaded = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for corrupt input
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise UserError(f"cannot read mesh file {path} ({reason[:120]}): {fix}") from None
    if not isinstance(loaded, trimesh.Trimesh):
        raise UserError(f"mesh file {path} contains no triangles: {fix}")
    faces = np.asarray(loaded.faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) and (faces.min() < 0 or faces.max() >= len(loaded.vertices)):
        raise UserError(
            f"mesh file {path} has faces with vertex indices outside 0..{len(loaded.vertices) - 1}: "
            f"the file is damaged; {fix}"
        )
    if not np.isfinite(np.asarray(loaded.vertices, dtype=np.float64)).all():
        raise UserError(f"mesh file {path} has NaN or infinite coordinates: {fix}")
    if len(faces):
        loaded.merge_vertices(merge_tex=True, merge_norm=True)
    return np.asarray(loaded.vertices, dtype=np.float64), np.asarray(loaded.faces, dtype=np.int64), None


def scan_normals(path: Path, cloud: trimesh.PointCloud) -> np.ndarray | None:
    """The unit normal of each point of the point cloud ``cloud`` read from ``path``, when the file
    holds one for every point (PLY ``nx ny nz``, which trimesh's reader keeps in the cloud's
    metadata; XYZ columns 4 to 6, which it drops); None otherwise (absent, zero, not of unit length:
    an XYZ file's columns 4 to 6 may be a colour)."""
    try:
        if path.suffix.lower() == ".xyz":
            table = np.loadtxt(path, ndmin=2, comments="#")
            normals = table[:, 3:6] if table.shape[1] >= 6 else None
        else:
            fields = _ply_vertex_fields(cloud)
            axes = ("nx", "ny", "nz")
            normals = np.column_stack([fields[n] for n in axes]) if set(axes) <= set(fields) else None
    except (ValueError, OSError):
        return None
    if normals is None or normals.shape != (len(cloud.vertices), 3):
        return None
    normals = normals.astype(np.float64)
    length = np.linalg.norm(normals, axis=1)
    return normals if np.isfinite(normals).all() and np.all(np.abs(length - 1.0) < 0.1) else None


def _ply_vertex_fields(cloud: trimesh.PointCloud) -> dict[str, np.ndarray]:
    """A PLY file's per-vertex properties by name, as trimesh's reader keeps them; {} for other files."""
    vertex = cloud.metadata.get("_ply_raw", {}).get("vertex", {}).get("data")
    if isinstance(vertex, dict):  # an ASCII file
        return vertex
    return {} if vertex is None else {name: vertex[name] for name in vertex.dtype.names or ()}


def read_mesh_file(path: Path, poisson_depth: int = 7) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """``(vertices (n,3) float64, faces (m,3) int64, repairs)`` of a mesh or point-cloud file.

    Coincident vertices (OBJ texture/normal seams, STL triangle soups) are merged so the surface
    is connected; a point cloud is reconstructed (``repairs`` says so). Raises :class:`UserError`
    naming the file and the fix for anything unreadable.
    """
    fix = "export it again as a binary PLY, OBJ, STL, OFF or GLB triangle mesh"
    if path.is_dir():
        raise UserError(f"mesh path {path} is a folder, not a file: name the mesh file inside it")
    if not path.is_file():
        raise UserError(f"mesh file {path} does not exist: check the path (or use builtin:bunny)")
    if path.stat().st_size == 0:
        raise UserError(f"mesh file {path} is empty: {fix}")
    if path.suffix.lower() not in SUPPORTED_SUFFIXES:
        raise UserError(
            f"mesh file {path} has an unsupported extension {path.suffix!r}: "
            f"use one of {', '.join(SUPPORTED_SUFFIXES)}"
        )
    vertices, faces, normals = read_geometry(path, fix)
    if not np.isfinite(vertices).all():  # a point cloud's points
        raise UserError(f"mesh file {path} has NaN or infinite coordinates: {fix}")
    repairs: tuple[str, ...] = ()
    if len(faces) == 0:
        if len(vertices) == 0:
            raise UserError(f"mesh file {path} contains no triangles: {fix}")
        point_count = len(vertices)
        surface = reconstruct_from_points(vertices, poisson_depth, f"mesh file {path}", normals)
        vertices, faces = surface.vertices, surface.faces
        thinned = f", one in {surface.stride} kept" if surface.stride > 1 else ""
        dropped = f", {surface.strays:,} stray point(s) far from the rest dropped" if surface.strays else ""
        tries = "".join(f"; {tried} gave {genus} handle(s)" for tried, genus in surface.handles.items())
        repairs = (
            f"{RECONSTRUCTED} {point_count:,} points{thinned}{dropped} "
            f"(screened Poisson, depth {surface.depth}, {surface.normals}{tries}): {len(faces):,} faces",
        )
    return np.ascontiguousarray(vertices), np.ascontiguousarray(faces), repairs


@node("mesh.load", params=LoadParams, outputs=("mesh",))
def load_mesh(params: LoadParams) -> Mesh:
    """Read a triangle mesh and convert its declared units to mm (``unitless`` keeps the numbers)."""
    path = resolve_mesh_path(params.path)
    vertices, faces, repairs = read_mesh_file(path, params.poisson_depth)
    source_name = params.path if params.path.startswith("builtin:") else str(path)
    return Mesh(
        vertices=vertices * MM_PER_UNIT[params.units],
        faces=faces,
        source=f"{source_name} sha256:{file_sha256(str(path))}",
        repairs=repairs,
    )


class ScaleParams(NodeParams):
    """At most one of ``units``, ``diagonal_mm`` or ``longest_extent_mm`` sets the scale; none keeps
    the numbers as mm (the size a file declared with ``mesh.load``'s ``units`` keeps its real size)."""

    units: Literal["mm", "cm", "m", "in"] | None = Field(
        None, description="the mesh's numbers are in this unit: multiply by mm per unit"
    )
    diagonal_mm: float | None = Field(
        None, ge=OBJECT_DIAGONAL_RANGE_MM[0], le=OBJECT_DIAGONAL_RANGE_MM[1], description="target bounding-box diagonal (mm)"
    )
    longest_extent_mm: float | None = Field(
        None, ge=OBJECT_DIAGONAL_RANGE_MM[0] / math.sqrt(3.0), le=OBJECT_DIAGONAL_RANGE_MM[1],
        description="target longest bounding-box side (mm)",
    )
    about: Literal["origin", "bbox_center"] = Field(
        "origin", description="fixed point of the scaling: the coordinate origin or the bbox centre"
    )

    @property
    def keeps_size(self) -> bool:
        """No target set: the numbers stay as ``mesh.load`` converted them (mm)."""
        return self.units is None and self.diagonal_mm is None and self.longest_extent_mm is None

    @model_validator(mode="after")
    def _at_most_one_target(self) -> "ScaleParams":
        given = [k for k in ("units", "diagonal_mm", "longest_extent_mm") if getattr(self, k) is not None]
        if len(given) > 1:
            raise ValueError(f"set at most one of units, diagonal_mm, longest_extent_mm (got {', '.join(given)})")
        return self


def scale_factor(vertices: np.ndarray, params: ScaleParams) -> float:
    """The uniform factor that gives ``vertices`` the size ``params`` asks for."""
    if params.units is not None:
        return MM_PER_UNIT[params.units]
    if params.keeps_size:
        return 1.0
    extents = vertices.max(axis=0) - vertices.min(axis=0)
    current = float(np.linalg.norm(extents)) if params.diagonal_mm is not None else float(extents.max())
    if current <= 0.0:
        raise UserError("the mesh has zero size (all vertices coincide): load a real mesh")
    target = params.diagonal_mm if params.diagonal_mm is not None else params.longest_extent_mm
    return float(target) / current


@node("mesh.scale", params=ScaleParams, inputs=("mesh",), outputs=("mesh",))
def scale_mesh(params: ScaleParams, mesh: Mesh) -> Mesh:
    """Scale uniformly to a physical size in mm, about the origin or the bounding-box centre.

    Geometry is otherwise untouched (no recentering, no rotation): with ``about: origin`` the
    coordinates are simply multiplied by the factor.
    """
    factor = scale_factor(mesh.vertices, params)
    if params.about == "origin":
        vertices = mesh.vertices * factor
    else:
        centre = 0.5 * (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0))
        vertices = (mesh.vertices - centre) * factor + centre
    diagonal = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    low, high = OBJECT_DIAGONAL_RANGE_MM
    if not low * (1 - 1e-9) <= diagonal <= high * (1 + 1e-9):
        read_in = f" read in {params.units}" if params.units else " as loaded" if params.keeps_size else ""
        fix = "check the file's units"
        in_metres = low <= diagonal * MM_PER_UNIT["m"] <= high
        if params.keeps_size and in_metres and Path(mesh.source_name).suffix.lower() in GLTF_SUFFIXES:
            fix = "glTF stores metres: set units: m"
        raise UserError(
            f"the object is {diagonal:.3g} mm across (bounding-box diagonal){read_in}: the method covers "
            f"{low:g} to {high:g} mm; {fix}, or set diagonal_mm to its real size"
        )
    return dataclasses.replace(mesh, vertices=vertices)
