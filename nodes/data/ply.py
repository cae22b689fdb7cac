"""The project's one PLY writer: binary little-endian triangle meshes in millimetres.

``vertex`` elements carry ``double x, y, z`` (mm), ``face`` elements a ``uchar``-counted ``int``
index list, CCW seen from outside; vertex and face order are kept exactly (events and sensing maps
refer to face indices).
"""
from __future__ import annotations

import numpy as np


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
