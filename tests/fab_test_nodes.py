"""A node type giving a synthetic sphere layout, so the fabrication nodes can run inside the engine
in tests (registered through ``RETROTOUCH_NODE_MODULES=fab_test_nodes``)."""
from __future__ import annotations

import trimesh
from fab_layouts import mesh_from_trimesh, section_layout
from pydantic import Field

from retrotouch.graph.node import NodeParams, node


class SphereLayoutParams(NodeParams):
    radius_mm: float = Field(40.0, gt=0, description="sphere radius (mm)")
    tx: int = Field(3, ge=1, description="meridians (Tx)")
    rx: int = Field(2, ge=1, description="horizontal sections (Rx)")


@node("fabtest.sphere_layout", params=SphereLayoutParams, outputs=("mesh", "layout"))
def sphere_layout(params: SphereLayoutParams) -> dict:
    """An icosphere with plane-section Tx/Rx curves and their crossings."""
    mesh = mesh_from_trimesh(trimesh.creation.icosphere(subdivisions=3, radius=params.radius_mm), "icosphere")
    return {"mesh": mesh, "layout": section_layout(mesh, params.tx, params.rx)}
