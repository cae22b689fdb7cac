"""Mesh ingest: read a mesh file (or the embedded bunny) and scale it to a physical size in mm.

Nodes:

* ``mesh.load``  -- OBJ/PLY/STL/OFF/GLB via trimesh (a GLB scene is flattened into one mesh), or
  ``builtin:bunny`` (pymeshlab's bundled Stanford bunny). The declared ``units`` convert the file's
  numbers to millimetres; ``unitless`` keeps them as they are (follow with ``mesh.scale``).
  ``Mesh.source`` is ``"<path> sha256:<hex of the file bytes>"``; ``Params.input_files()`` names
  the file so the engine keys the cache on its content.
* ``mesh.scale`` -- uniform scaling to a physical size: a unit factor, a bounding-box diagonal or a
  longest bounding-box extent, about the origin (default) or the bounding-box centre.
"""
from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Literal

import numpy as np
import trimesh
from pydantic import Field, model_validator

from ...graph.errors import UserError
from ...graph.node import NodeParams, node
from ..data.builtin import builtin_mesh_path
from ..data.types import Mesh

MM_PER_UNIT = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4, "unitless": 1.0}
"""Millimetres per declared unit (``unitless`` keeps the numbers; scale afterwards)."""

SUPPORTED_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")


def resolve_mesh_path(path: str) -> Path:
    """The file behind ``path``: a ``builtin:`` name resolves inside the installed pymeshlab."""
    if path.startswith("builtin:"):
        return builtin_mesh_path(path)
    return Path(path).expanduser()


class LoadParams(NodeParams):
    """Where the mesh comes from and what unit its numbers are in."""

    path: str = Field("builtin:bunny", description="mesh file (OBJ/PLY/STL/OFF/GLB) or builtin:bunny")
    units: Literal["mm", "cm", "m", "in", "unitless"] = Field(
        "unitless", description="unit of the file's coordinates; unitless = keep numbers, scale later"
    )

    def input_files(self) -> list[str]:
        return [str(resolve_mesh_path(self.path))]


def file_sha256(path: Path) -> str:
    """Hex sha256 of a file's bytes."""
    digest = hashlib.sha256()
    with path.open("rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def read_mesh_file(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (n,3) float64, faces (m,3) int64)`` of a mesh file, scenes flattened.

    Coincident vertices (OBJ texture/normal seams, STL triangle soups) are merged so the surface
    is connected. Raises :class:`UserError` naming the file and the fix for anything unreadable.
    """
    fix = "export it again as a binary PLY, OBJ, STL, OFF or GLB triangle mesh"
    if not path.is_file():
        raise UserError(f"mesh file {path} does not exist: check the path (or use builtin:bunny)")
    if path.stat().st_size == 0:
        raise UserError(f"mesh file {path} is empty: {fix}")
    if path.suffix.lower() not in SUPPORTED_SUFFIXES:
        raise UserError(
            f"mesh file {path} has an unsupported extension {path.suffix!r}: "
            f"use one of {', '.join(SUPPORTED_SUFFIXES)}"
        )
    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for corrupt input
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise UserError(f"cannot read mesh file {path} ({reason[:120]}): {fix}") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise UserError(f"mesh file {path} contains no triangles: {fix}")
    loaded.merge_vertices(merge_tex=True, merge_norm=True)
    vertices = np.ascontiguousarray(loaded.vertices, dtype=np.float64)
    faces = np.ascontiguousarray(loaded.faces, dtype=np.int64)
    if not np.isfinite(vertices).all():
        raise UserError(f"mesh file {path} has NaN or infinite coordinates: {fix}")
    return vertices, faces


@node("mesh.load", params=LoadParams, outputs=("mesh",))
def load_mesh(params: LoadParams) -> Mesh:
    """Read a triangle mesh and convert its declared units to mm (``unitless`` keeps the numbers)."""
    path = resolve_mesh_path(params.path)
    vertices, faces = read_mesh_file(path)
    source_name = params.path if params.path.startswith("builtin:") else str(path)
    return Mesh(
        vertices=vertices * MM_PER_UNIT[params.units],
        faces=faces,
        source=f"{source_name} sha256:{file_sha256(path)}",
    )


class ScaleParams(NodeParams):
    """Exactly one of ``units``, ``diagonal_mm`` or ``longest_extent_mm`` sets the scale."""

    units: Literal["mm", "cm", "m", "in"] | None = Field(
        None, description="the mesh's numbers are in this unit: multiply by mm per unit"
    )
    diagonal_mm: float | None = Field(None, gt=0, description="target bounding-box diagonal (mm)")
    longest_extent_mm: float | None = Field(
        None, gt=0, description="target longest bounding-box side (mm)"
    )
    about: Literal["origin", "bbox_center"] = Field(
        "origin", description="fixed point of the scaling: the coordinate origin or the bbox centre"
    )

    @model_validator(mode="after")
    def _exactly_one_target(self) -> "ScaleParams":
        given = [k for k in ("units", "diagonal_mm", "longest_extent_mm") if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError(
                "set exactly one of units, diagonal_mm, longest_extent_mm"
                + (f" (got {', '.join(given)})" if given else "")
            )
        return self


def scale_factor(vertices: np.ndarray, params: ScaleParams) -> float:
    """The uniform factor that gives ``vertices`` the size ``params`` asks for."""
    if params.units is not None:
        return MM_PER_UNIT[params.units]
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
    return Mesh(vertices=vertices, faces=mesh.faces, source=mesh.source)
