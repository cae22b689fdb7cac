"""Meshes that ship with a dependency, located once for the project.

``builtin:bunny`` is pymeshlab's bundled Stanford bunny (``tests/sample_meshes/bunny.obj`` inside
the installed package); in its file coordinates it rests on its base with ``+y`` up.
"""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

from ...graph.errors import UserError

BUILTIN_MESHES = {"builtin:bunny": "tests/sample_meshes/bunny.obj"}
"""Embedded meshes: name -> path inside the installed pymeshlab package."""

BUNNY_UP = np.array([0.0, 1.0, 0.0])
"""Up axis of ``builtin:bunny`` in its file coordinates (opposite to the side it rests on)."""


def builtin_mesh_path(name: str) -> Path:
    """The file behind a ``builtin:`` mesh name; one-line UserError for an unknown name or a
    missing pymeshlab."""
    if name not in BUILTIN_MESHES:
        raise UserError(f"unknown built-in mesh {name!r}: use one of {', '.join(sorted(BUILTIN_MESHES))} "
                        "or a file path")
    spec = importlib.util.find_spec("pymeshlab")
    if spec is None or spec.origin is None:
        raise UserError("pymeshlab is not installed: pip install pymeshlab")
    path = Path(spec.origin).parent / BUILTIN_MESHES[name]
    if not path.is_file():
        raise UserError(f"pymeshlab's sample mesh is missing ({path}): reinstall pymeshlab")
    return path
