"""``layout.sensing_map``: the files the runtime reads (sensing_map.json, mesh.ply, metrics.json).

``sensing_map.json`` follows :data:`retrotouch.nodes.data.types.SENSING_MAP_FORMAT` exactly. Cell
normals are the unit area-weighted vertex normals interpolated with the cell's barycentrics (smooth
across faces, outward because faces are CCW from outside). ``mesh.ply`` is the processed mesh as
binary PLY (trimesh); its sha256 is written into the sensing map.
"""
from __future__ import annotations

import hashlib
import json

import numpy as np

from ...graph.node import Files, NodeParams, node
from ..data.types import SENSING_MAP_FORMAT, Layout, Mesh


def mesh_ply_bytes(mesh: Mesh) -> bytes:
    """Binary PLY of the mesh, vertices and faces in order (no merging or reordering)."""
    import trimesh  # heavy: imported when writing, not on node discovery

    return trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(file_type="ply", encoding="binary")


def cell_normals(mesh: Mesh, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Unit normals at surface points from barycentric interpolation of area-weighted vertex normals."""
    P = mesh.vertices[mesh.faces]
    face_n = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])  # length = 2 * area
    vertex_n = np.zeros_like(mesh.vertices)
    for corner in range(3):
        np.add.at(vertex_n, mesh.faces[:, corner], face_n)
    n = np.einsum("kc,kcd->kd", bary, vertex_n[mesh.faces[faces]])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def sensing_map(layout: Layout, mesh: Mesh, mesh_bytes: bytes) -> dict:
    """The sensing_map.json document for a layout on a mesh whose PLY bytes are ``mesh_bytes``."""
    cells = layout.cells
    normals = cell_normals(mesh, cells.faces, cells.bary)

    def channels(curves, source, prefix):
        return [{"channel": i, "name": f"{prefix}{i:02d}", "curve": int(source[i]),
                 "length_mm": float(curves.lengths_mm[i])} for i in range(curves.count)]

    return {
        "format": SENSING_MAP_FORMAT,
        "units": "mm",
        "mesh": {"file": "mesh.ply", "sha256": hashlib.sha256(mesh_bytes).hexdigest(),
                 "vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces))},
        "design": {"pad_radius_mm": float(layout.pad_radius_mm), "d_min_mm": float(layout.d_min_mm),
                   "trace_width_mm": float(layout.trace_width_mm), "clearance_mm": float(layout.clearance_mm)},
        "tx_channels": int(layout.tx.count),
        "rx_channels": int(layout.rx.count),
        "channels": {"tx": channels(layout.tx, layout.tx_source, "Tx"),
                     "rx": channels(layout.rx, layout.rx_source, "Rx")},
        "cells": [{"tx": int(cells.curve_a[k]), "rx": int(cells.curve_b[k]),
                   "point": [float(v) for v in cells.points[k]], "face": int(cells.faces[k]),
                   "bary": [float(v) for v in cells.bary[k]], "normal": [float(v) for v in normals[k]],
                   "pad": bool(layout.pad[k])} for k in range(len(cells.curve_a))],
    }


class SensingMapParams(NodeParams):
    """No parameters: the file layout is fixed by the format."""


@node("layout.sensing_map", params=SensingMapParams, inputs=("mesh", "layout", "metrics"),
      outputs=("files",), sink=True)
def write_sensing_map(params: SensingMapParams, mesh: Mesh, layout: Layout, metrics: dict) -> Files:
    """sensing_map.json (channel pairs -> crossing point, face, barycentrics, normal, pad), mesh.ply, metrics.json."""
    ply = mesh_ply_bytes(mesh)
    document = sensing_map(layout, mesh, ply)
    return Files({
        "sensing_map.json": json.dumps(document, indent=1).encode(),
        "mesh.ply": ply,
        "metrics.json": json.dumps(metrics, indent=1, default=_json_default).encode(),
    })


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"metrics value of type {type(value).__name__} is not JSON serialisable")
