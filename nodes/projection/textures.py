"""Projection textures: the layout baked into a UV texture of the object (sink ``projection.textures``).

An xatlas atlas of the faces the layout paints (``padding_px`` gutter, ``texture_px`` square;
:mod:`.atlas`) parametrises the mesh; the other faces show the background. Each curve segment
lies inside one face (``CurveSet`` convention), so both its ends are mapped to UV with
barycentrics of that face and drawn there: a line never jumps across a seam.
Crossings are drawn as rings and pads as filled discs in the UV of their face. Widths are given
in millimetres on the surface and converted with the atlas' mean texel density.

Files written (``<name>`` from ``Params.name`` or the mesh source):

* ``projection/<name>_layout.glb`` -- the textured mesh for glTF viewers (three.js, Blender,
  ``<model-viewer>``): positions in metres (glTF's unit), smooth vertex normals, one matte material
  (baseColorFactor 1 times the embedded PNG texture, metallicFactor 0, roughnessFactor
  :data:`GLB_ROUGHNESS`); ``asset.extras`` says ``{"units": "m", "face_order": "mesh.ply"}``.
  The vertices keep the mesh's frame; the one scene node's matrix (:func:`standing_transform`)
  stands the object in its resting pose in glTF's frame: the regions' up axis along +Y, the
  lowest point on the ground plane y = 0, the footprint centred on the Y axis,
* ``projection/<name>_layout.obj`` + ``.mtl`` + ``projection/<name>_texture.png`` (OBJ in mm),
* ``projection/<name>_scene.npz`` -- the curves, normals and crossings the projector renderer and
  ``retrotouch project`` read, plus the atlas and one projector texture per layer (black
  background, white curves) for the textured route (format: :mod:`retrotouch.nodes.data.scene`).

Face order: face ``k`` of the OBJ and of the GLB is face ``k`` of the run's ``mesh.ply`` (and of
the ``Mesh`` passed in), with the same corners in the same order; only vertices are split along
atlas seams. Anything that names a face id (sensing-map cells, touch events) indexes all three.

UV convention: OBJ/trimesh (origin bottom-left, v up); texture row = (1 - v) * size.
"""
from __future__ import annotations

import dataclasses
import json
import re
import struct
from pathlib import Path

import numpy as np
from pydantic import Field, field_validator

from ...graph.errors import UserError
from ...graph.node import Files, NodeParams, node
from ..data.scene import build_scene, save_scene
from ..data.types import CurveSet, Layout, Mesh, SurfaceRegions
from ..geometry.triangles import vertex_normals
from .atlas import Atlas, build_atlas, face_uv_pixels, layout_band, texels_per_mm

# Heavy libraries (cv2, trimesh, xatlas, PIL) are imported inside the functions: node modules must
# import cheaply (the engine imports them to discover node types).

HEX_COLOUR = re.compile(r"^#[0-9a-fA-F]{6}$")
GLB_ROUGHNESS = 0.9
"""Roughness of the GLB material: a matte foil/paint look, no mirror-like highlights."""
MM_PER_M = 1000.0


class TextureParams(NodeParams):
    """Texture size and look of the baked layout."""

    texture_px: int = Field(2048, ge=256, le=8192, description="texture width = height (px)")
    padding_px: int = Field(4, ge=0, le=32, description="gutter between atlas charts (px)")
    crossing_radius_mm: float = Field(1.0, gt=0, description="crossing ring radius (mm)")
    background: str = Field("#d8d8d8", description="texture background colour (#RRGGBB)")
    tx_colour: str = Field("#d03020", description="Tx curve colour (#RRGGBB)")
    rx_colour: str = Field("#2050d0", description="Rx curve colour (#RRGGBB)")
    crossing_colour: str = Field("#101010", description="crossing ring colour (#RRGGBB)")
    pad_colour: str = Field("#e0a000", description="pad disc colour (#RRGGBB)")
    name: str | None = Field(None, description="file name stem; default: taken from the mesh source")

    @field_validator("background", "tx_colour", "rx_colour", "crossing_colour", "pad_colour")
    @classmethod
    def _hex(cls, value: str) -> str:
        if not HEX_COLOUR.match(value):
            raise ValueError(f"colour {value!r} must look like #RRGGBB")
        return value

    @field_validator("name")
    @classmethod
    def _stem(cls, value: str | None) -> str | None:
        if value is not None and not re.fullmatch(r"[A-Za-z0-9_.-]+", value):
            raise ValueError(f"name {value!r} may only hold letters, digits, '_', '-' and '.'")
        return value


def _bgr(hex_colour: str) -> tuple[int, int, int]:
    r, g, b = (int(hex_colour[i : i + 2], 16) for i in (1, 3, 5))
    return (b, g, r)


def name_from_source(source: str) -> str:
    """A file-name stem from ``Mesh.source`` ('builtin:bunny ...' -> 'bunny', '/x/my duck.ply sha256:..' -> 'my_duck')."""
    first = re.sub(r"\s+sha256:[0-9a-fA-F]*$", "", source.strip()) or "mesh"
    stem = first.split(":", 1)[1] if first.startswith("builtin:") else Path(first).stem
    return re.sub(r"[^A-Za-z0-9_-]+", "_", stem) or "mesh"


def segment_uv_pixels(mesh: Mesh, atlas: Atlas, curves: CurveSet, texture_px: int) -> np.ndarray:
    """(S, 2, 2) texture pixel coordinates of every curve segment, both ends in the segment's own face."""
    import trimesh

    starts = np.concatenate(
        [np.arange(curves.offsets[c], curves.offsets[c + 1] - 1) for c in range(curves.count)] + [np.zeros(0, np.int64)]
    ).astype(np.int64)
    if len(starts) == 0:
        return np.zeros((0, 2, 2))
    seg_faces = curves.faces[starts]
    tri = mesh.vertices[mesh.faces[seg_faces]]
    end_bary = trimesh.triangles.points_to_barycentric(tri, curves.points[starts + 1])
    a = face_uv_pixels(atlas, seg_faces, curves.bary[starts], texture_px)
    b = face_uv_pixels(atlas, seg_faces, end_bary, texture_px)
    return np.stack([a, b], axis=1)


def _bake(
    mesh: Mesh,
    layout: Layout,
    atlas: Atlas,
    params: TextureParams,
    background: tuple[int, int, int],
    curves: list[tuple[CurveSet, tuple[int, int, int]]],
    crossing_bgr: tuple[int, int, int],
    pad_bgr: tuple[int, int, int],
) -> np.ndarray:
    import cv2

    size = params.texture_px
    img = np.zeros((size, size, 3), np.uint8)
    img[:] = background
    density = texels_per_mm(mesh, atlas, size)
    shift = 4
    scale = float(1 << shift)
    width = max(1, int(round(layout.trace_width_mm * density)))
    for curve_set, colour in curves:
        segs = segment_uv_pixels(mesh, atlas, curve_set, size)
        if len(segs):
            cv2.polylines(img, list(np.rint(segs * scale).astype(np.int32)), False, colour, width, cv2.LINE_AA, shift)
    centres = np.rint(face_uv_pixels(atlas, layout.cells.faces, layout.cells.bary, size) * scale).astype(np.int64)
    pad_r = int(round(layout.pad_radius_mm * density * scale))
    ring_r = int(round(params.crossing_radius_mm * density * scale))
    ring_w = max(1, width // 2)
    for (x, y), has_pad in zip(centres, np.asarray(layout.pad, bool)):
        if has_pad:
            cv2.circle(img, (int(x), int(y)), pad_r, pad_bgr, -1, cv2.LINE_AA, shift)
        cv2.circle(img, (int(x), int(y)), ring_r, crossing_bgr, ring_w, cv2.LINE_AA, shift)
    return img


def bake_texture(mesh: Mesh, layout: Layout, atlas: Atlas, params: TextureParams) -> np.ndarray:
    """The BGR uint8 texture (texture_px, texture_px, 3) with both layers' curves, crossings and pads."""
    curves = [(layout.tx, _bgr(params.tx_colour)), (layout.rx, _bgr(params.rx_colour))]
    return _bake(mesh, layout, atlas, params, _bgr(params.background), curves, _bgr(params.crossing_colour), _bgr(params.pad_colour))


def bake_projector_texture(mesh: Mesh, layout: Layout, atlas: Atlas, params: TextureParams, layer: str) -> np.ndarray:
    """One layer baked for projection: black (no light), the layer's curves white, crossing rings and pads in colour."""
    curve_set = layout.tx if layer == "tx" else layout.rx
    white = (255, 255, 255)
    return _bake(mesh, layout, atlas, params, (0, 0, 0), [(curve_set, white)], (0, 255, 255), _bgr(params.pad_colour))


def obj_text(mesh: Mesh, atlas: Atlas, mtl_file: str) -> str:
    """Wavefront OBJ of the split-vertex atlas mesh (one ``vt`` per vertex, 1-based ``f v/vt``)."""
    v = mesh.vertices[atlas.vertex_map]
    f = np.repeat(atlas.faces + 1, 2, axis=1)
    lines = [
        f"# retrotouch projection texture mesh (mm)\nmtllib {mtl_file}\no layout\n",
        ("v %.6f %.6f %.6f\n" * len(v)) % tuple(v.ravel().tolist()),
        ("vt %.6f %.6f\n" * len(atlas.uv)) % tuple(atlas.uv.ravel().tolist()),
        "usemtl layout\n",
        ("f %d/%d %d/%d %d/%d\n" * len(f)) % tuple(f.ravel().tolist()),
    ]
    return "".join(lines)


def standing_transform(vertices_m: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(4, 4) rigid transform (metres) taking ``up`` to +Y, the lowest vertex to y = 0 and the
    bounding-box centre of the footprint (x, z) to the origin."""
    from scipy.spatial.transform import Rotation

    rotation = Rotation.align_vectors([[0.0, 1.0, 0.0]], [np.asarray(up, np.float64)])[0].as_matrix()
    turned = vertices_m @ rotation.T
    low, high = turned.min(axis=0), turned.max(axis=0)
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = [-(low[0] + high[0]) / 2, -low[1], -(low[2] + high[2]) / 2]
    return transform


def glb_bytes(mesh: Mesh, atlas: Atlas, texture_png: bytes, up: np.ndarray) -> bytes:
    """The GLB described in the module docstring (metres, matte material, ``texture_png`` embedded
    as it is, mesh face order, standing with ``up`` along +Y)."""
    import trimesh
    from PIL import Image

    material = trimesh.visual.material.PBRMaterial(
        name="layout",
        baseColorTexture=Image.new("RGB", (1, 1)),  # a placeholder: the PNG goes in by with_png_image
        baseColorFactor=[255, 255, 255, 255],
        metallicFactor=0.0,
        roughnessFactor=GLB_ROUGHNESS,
    )
    normals = vertex_normals(mesh.vertices, mesh.faces)[atlas.vertex_map]
    vertices_m = mesh.vertices[atlas.vertex_map] / MM_PER_M
    textured = trimesh.Trimesh(
        vertices=vertices_m,
        faces=atlas.faces,
        vertex_normals=normals,
        visual=trimesh.visual.TextureVisuals(uv=atlas.uv, material=material),
        process=False,
    )

    def describe(tree: dict) -> None:
        tree["asset"]["extras"] = {"units": "m", "face_order": "mesh.ply"}

    scene = trimesh.Scene()
    scene.add_geometry(textured, node_name="object", geom_name="layout", transform=standing_transform(vertices_m, up))
    glb = bytes(trimesh.exchange.gltf.export_glb(scene, include_normals=True, tree_postprocessor=describe))
    return with_png_image(glb, texture_png)


def with_png_image(glb: bytes, png: bytes) -> bytes:
    """``glb`` (one buffer, one image) with the image's bytes replaced by ``png`` (no re-encoding)."""
    json_length = struct.unpack_from("<I", glb, 12)[0]
    tree = json.loads(glb[20 : 20 + json_length])
    blob = glb[20 + json_length + 8 :]
    image_view = tree["images"][0]["bufferView"]
    parts, offset = [], 0
    for index, view in enumerate(tree["bufferViews"]):
        start = view.get("byteOffset", 0)
        data = png if index == image_view else blob[start : start + view["byteLength"]]
        view["byteOffset"], view["byteLength"] = offset, len(data)
        parts.append(data + b"\0" * (-len(data) % 4))
        offset += len(parts[-1])
    binary = b"".join(parts)
    tree["buffers"][0]["byteLength"] = len(binary)
    text = json.dumps(tree, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<I4s", len(text), b"JSON") + text + struct.pack("<I4s", len(binary), b"BIN\0") + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks


def mtl_text(texture_file: str) -> str:
    return f"newmtl layout\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nd 1\nillum 1\nmap_Kd {texture_file}\n"


def paint_reach_mm(params: TextureParams, layout: Layout) -> tuple[float, float]:
    """How far (mm) paint reaches from a curve and from a crossing (the layout's pad disc or a ring)."""
    line = layout.trace_width_mm / 2
    return line, max(layout.pad_radius_mm, params.crossing_radius_mm + line)


def layout_atlas(mesh: Mesh, layout: Layout, params: TextureParams) -> Atlas:
    """The atlas the sink bakes into: charts for the faces within paint reach of the layout."""
    line_reach, cell_reach = paint_reach_mm(params, layout)
    band = layout_band(mesh, layout, params.texture_px, line_reach, cell_reach)
    return build_atlas(mesh, params.texture_px, params.padding_px, band, max(line_reach, cell_reach))


def check_layout_on_mesh(mesh: Mesh, layout: Layout) -> None:
    """UserError when the layout's face ids do not fit the mesh."""
    m = len(mesh.faces)
    for what, faces in (("tx", layout.tx.faces), ("rx", layout.rx.faces), ("cells", layout.cells.faces)):
        if len(faces) and (faces.min() < 0 or faces.max() >= m):
            raise UserError(f"layout {what} refers to face {int(faces.max())} but the mesh has {m} faces: pass the mesh the layout was made on")


@node("projection.textures", params=TextureParams, inputs=("mesh", "regions", "layout"), outputs=("files",), sink=True)
def projection_textures(params: TextureParams, mesh: Mesh, regions: SurfaceRegions, layout: Layout) -> Files:
    """Bake the selected curves (per-layer colour), crossings and pads into a UV texture; write GLB, OBJ+MTL+PNG and the projection scene."""
    import cv2

    check_layout_on_mesh(mesh, layout)
    stem = params.name or name_from_source(mesh.source)
    atlas = layout_atlas(mesh, layout, params)
    texture = bake_texture(mesh, layout, atlas, params)
    ok, encoded = cv2.imencode(".png", texture)
    if not ok:
        raise RuntimeError("PNG encoding of the texture failed")
    png = encoded.tobytes()
    base = f"projection/{stem}"
    scene = dataclasses.replace(
        build_scene(mesh, layout),
        atlas_vertex_map=atlas.vertex_map,
        atlas_faces=atlas.faces,
        atlas_uv=atlas.uv,
        layer_textures=tuple(bake_projector_texture(mesh, layout, atlas, params, layer) for layer in ("tx", "rx")),
    )
    return Files(
        {
            f"{base}_layout.glb": glb_bytes(mesh, atlas, png, regions.up),
            f"{base}_layout.obj": obj_text(mesh, atlas, f"{stem}_layout.mtl").encode(),
            f"{base}_layout.mtl": mtl_text(f"{stem}_texture.png").encode(),
            f"{base}_texture.png": png,
            f"{base}_scene.npz": save_scene(scene),
        }
    )
