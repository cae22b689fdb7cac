"""Sink ``mesh.export``: the processed mesh as a binary PLY file in the run's output folder.

The file is written by :func:`..data.ply.ply_bytes` (binary PLY in millimetres, CCW outward).
"""
from __future__ import annotations

from pydantic import Field, field_validator

from ...graph.node import Files, NodeParams, node
from ..data.ply import ply_bytes
from ..data.types import Mesh


class ExportParams(NodeParams):
    """Name of the file written into the output folder."""

    filename: str = Field("mesh.ply", description="output file name (relative, ends with .ply)")

    @field_validator("filename")
    @classmethod
    def _ply_name(cls, value: str) -> str:
        if not value.endswith(".ply") or value.startswith(("/", "..")):
            raise ValueError("must be a relative file name ending with .ply, e.g. mesh.ply")
        return value


@node("mesh.export", params=ExportParams, inputs=("mesh",), outputs=("files",), sink=True)
def export_mesh(params: ExportParams, mesh: Mesh) -> Files:
    """Write the mesh (mm, CCW outward) as a binary PLY file into the output folder."""
    return Files({params.filename: ply_bytes(mesh.vertices, mesh.faces, comment=f"retrotouch mesh in mm from {mesh.source}")})
