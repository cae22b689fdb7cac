"""The projection scene file (``projection/<name>_scene.npz``): what the projector runtime needs.

Written by the ``projection.textures`` sink, read by ``retrotouch project``. An ``.npz`` (no pickle)
with these arrays, all in the object (mesh) frame, millimetres:

* ``format`` -- :data:`SCENE_FORMAT`; ``vertices`` (n, 3) float64, ``faces`` (m, 3) int64;
* ``layer_names`` -- the layers in attachment order (Tx first);
* ``layer<k>_points`` (P, 3) float64 / ``layer<k>_normals`` (P, 3) unit / ``layer<k>_offsets`` (C + 1,)
  int64 -- layer ``k``'s polylines: curve ``c`` owns rows ``offsets[c]:offsets[c + 1]`` (surface
  points and their interpolated vertex normals);
* ``crossing_points`` / ``crossing_normals`` (K, 3) -- the Tx x Rx crossings; ``pad`` (K,) bool --
  those that carry an electrode pad;
* optional texture route: ``atlas_vertex_map`` (n',) int64 (split vertices into ``vertices``),
  ``atlas_faces`` (m, 3) int64 (the mesh's face order), ``atlas_uv`` (n', 2) float64 (OBJ
  convention: origin bottom-left, v up), ``layer<k>_texture_png`` -- layer ``k`` baked into the atlas
  as a projector image (PNG bytes of a BGR image, black = no light).
"""
from __future__ import annotations

import dataclasses
import io
from pathlib import Path

import cv2
import numpy as np

from ...graph.errors import UserError
from ..geometry.triangles import surface_normals
from .types import CurveSet, Layout, Mesh

SCENE_FORMAT = "retrotouch.projection_scene/2"


@dataclasses.dataclass(frozen=True)
class ProjectionScene:
    """The scene file's content (see the module docstring); textures decoded to BGR uint8 images."""

    vertices: np.ndarray  # (n, 3) float64
    faces: np.ndarray  # (m, 3) int64
    layer_names: tuple[str, ...]
    layer_points: tuple[np.ndarray, ...]
    layer_normals: tuple[np.ndarray, ...]
    layer_offsets: tuple[np.ndarray, ...]
    crossing_points: np.ndarray  # (K, 3)
    crossing_normals: np.ndarray  # (K, 3)
    pad: np.ndarray  # (K,) bool
    pad_radius_mm: float  # the layout's electrode pad radius
    atlas_vertex_map: np.ndarray | None = None  # (n',) int64
    atlas_faces: np.ndarray | None = None  # (m, 3) int64
    atlas_uv: np.ndarray | None = None  # (n', 2) float64
    layer_textures: tuple[np.ndarray, ...] = ()


def build_scene(mesh: Mesh, layout: Layout) -> ProjectionScene:
    """Collect the layout's curves, crossings and pads with their surface normals (Tx layer first)."""
    sets: tuple[CurveSet, ...] = (layout.tx, layout.rx)
    return ProjectionScene(
        vertices=np.asarray(mesh.vertices, np.float64),
        faces=np.asarray(mesh.faces, np.int64),
        layer_names=tuple(s.layer for s in sets),
        layer_points=tuple(np.asarray(s.points, np.float64) for s in sets),
        layer_normals=tuple(surface_normals(mesh.vertices, mesh.faces, s.faces, s.bary) for s in sets),
        layer_offsets=tuple(np.asarray(s.offsets, np.int64) for s in sets),
        crossing_points=np.asarray(layout.cells.points, np.float64),
        crossing_normals=surface_normals(mesh.vertices, mesh.faces, layout.cells.faces, layout.cells.bary),
        pad=np.asarray(layout.pad, bool),
        pad_radius_mm=float(layout.pad_radius_mm),
    )


def save_scene(scene: ProjectionScene) -> bytes:
    """Serialise a scene as ``.npz`` bytes (no pickle)."""
    arrays: dict[str, np.ndarray] = {
        "format": np.array(SCENE_FORMAT),
        "vertices": scene.vertices,
        "faces": scene.faces,
        "layer_names": np.array(scene.layer_names),
        "crossing_points": scene.crossing_points,
        "crossing_normals": scene.crossing_normals,
        "pad": scene.pad,
        "pad_radius_mm": np.array(scene.pad_radius_mm),
    }
    if scene.atlas_uv is not None:
        arrays["atlas_vertex_map"] = scene.atlas_vertex_map
        arrays["atlas_faces"] = scene.atlas_faces
        arrays["atlas_uv"] = scene.atlas_uv
        for i, tex in enumerate(scene.layer_textures):
            ok, png = cv2.imencode(".png", tex)
            if not ok:
                raise RuntimeError("PNG encoding of a layer texture failed")
            arrays[f"layer{i}_texture_png"] = png.ravel()
    for i in range(len(scene.layer_names)):
        arrays[f"layer{i}_points"] = scene.layer_points[i]
        arrays[f"layer{i}_normals"] = scene.layer_normals[i]
        arrays[f"layer{i}_offsets"] = scene.layer_offsets[i]
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def load_scene(path: Path) -> ProjectionScene:
    """Read a scene written by :func:`save_scene`; UserError when the file is not one."""
    try:
        data = np.load(path, allow_pickle=False)
        if str(data["format"]) != SCENE_FORMAT:
            raise UserError(f"{path} is {data['format']}, expected {SCENE_FORMAT}: re-run the projection.textures sink")
        names = tuple(str(n) for n in data["layer_names"])
        textured = "atlas_uv" in data
        textures = tuple(
            cv2.imdecode(data[f"layer{i}_texture_png"], cv2.IMREAD_COLOR) for i in range(len(names))
        ) if textured else ()
        return ProjectionScene(
            vertices=data["vertices"],
            faces=data["faces"],
            layer_names=names,
            layer_points=tuple(data[f"layer{i}_points"] for i in range(len(names))),
            layer_normals=tuple(data[f"layer{i}_normals"] for i in range(len(names))),
            layer_offsets=tuple(data[f"layer{i}_offsets"] for i in range(len(names))),
            crossing_points=data["crossing_points"],
            crossing_normals=data["crossing_normals"],
            pad=data["pad"],
            pad_radius_mm=float(data["pad_radius_mm"]),
            atlas_vertex_map=data["atlas_vertex_map"] if textured else None,
            atlas_faces=data["atlas_faces"] if textured else None,
            atlas_uv=data["atlas_uv"] if textured else None,
            layer_textures=textures,
        )
    except (OSError, KeyError, ValueError) as exc:
        raise UserError(f"cannot read projection scene {path}: {exc}; point --layout at a run folder with projection/*_scene.npz") from exc
