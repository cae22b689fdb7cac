"""Sink ``mesh.export``: the processed mesh as a binary PLY file in the run's output folder.

The file is little-endian binary PLY: ``vertex`` elements with ``double x, y, z`` in millimetres and
``face`` elements with a ``uchar``-counted ``int`` index list, CCW seen from outside (the
project-wide winding convention), so readers that take units from the numbers get millimetres.
"""
from __future__ import annotations

import numpy as np
from pydantic import Field, field_validator

from retrotouch.graph.node import Files, NodeParams, node
from retrotouch.nodes.datatypes import Mesh


class ExportParams(NodeParams):
    """Name of the file written into the output folder."""

    filename: str = Field("mesh.ply", description="output file name (relative, ends with .ply)")

    @field_validator("filename")
    @classmethod
    def _ply_name(cls, value: str) -> str:
        if not value.endswith(".ply") or value.startswith(("/", "..")):
            raise ValueError("must be a relative file name ending with .ply, e.g. mesh.ply")
        return value


def ply_bytes(vertices: np.ndarray, faces: np.ndarray, comment: str = "") -> bytes:
    """Binary little-endian PLY of a triangle mesh (vertices as float64, faces as int32)."""
    vertices = np.ascontiguousarray(vertices, dtype="<f8")
    faces = np.asarray(faces)
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError("face indices out of range")
    header = ["ply", "format binary_little_endian 1.0"]
    if comment:
        header.append("comment " + " ".join(comment.split()))
    header += [f"element vertex {len(vertices)}", "property double x", "property double y", "property double z",
               f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    face_rows = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face_rows["n"] = 3
    face_rows["v"] = faces
    return ("\n".join(header) + "\n").encode("ascii") + vertices.tobytes() + face_rows.tobytes()


@node("mesh.export", params=ExportParams, inputs=("mesh",), outputs=("files",), sink=True)
def export_mesh(params: ExportParams, mesh: Mesh) -> Files:
    """Write the mesh (mm, CCW outward) as a binary PLY file into the output folder."""
    return Files({params.filename: ply_bytes(mesh.vertices, mesh.faces, comment=f"retrotouch mesh in mm from {mesh.source}")})
