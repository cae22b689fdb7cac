"""The touch field of a test mesh (``regions.touchable`` with its defaults), computed once per mesh."""
from __future__ import annotations

import functools
import hashlib

import numpy as np

from retrotouch.nodes.data.types import Mesh, TouchField
from retrotouch.nodes.regions.touch import TouchParams, touch_field


@functools.lru_cache(maxsize=16)
def _field(_digest: str, vertices: bytes, faces: bytes) -> TouchField:
    V = np.frombuffer(vertices, dtype=np.float64).reshape(-1, 3)
    F = np.frombuffer(faces, dtype=np.int64).reshape(-1, 3)
    return touch_field(V, F, TouchParams())


def touch_of(mesh: Mesh) -> TouchField:
    """The default touch field of ``mesh`` (cached by content)."""
    V = np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes()
    F = np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes()
    return _field(hashlib.sha256(V + F).hexdigest(), V, F)
