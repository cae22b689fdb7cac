"""``layout.sensing_map``: the files the runtime reads (sensing_map.json, mesh.ply, metrics.json).

``sensing_map.json`` and ``mesh.ply`` come from the one writer,
:func:`retrotouch.nodes.data.sensing_map.sensing_map_files` (format and cell normals described
there); the up axis and the sensing region a finger can touch are what ``regions.detect`` found.
"""
from __future__ import annotations

import json

from ...graph.node import Files, NodeParams, node
from ..data.metrics_file import metrics_json
from ..data.sensing_map import sensing_map_files
from ..data.types import Layout, Mesh, SurfaceRegions
from .metrics import UNCOVERED_MM, limbs


class SensingMapParams(NodeParams):
    """No parameters: the file layout is fixed by the format."""


def limbs_note(files: Files) -> str | None:
    """The run summary's line: the limbs and the cells on them (none: no line)."""
    found = json.loads(files.contents["metrics.json"])["limbs"]
    if not found:
        return None
    cells = ", ".join(str(limb["cells"]) for limb in found)
    return (f"limbs: {len(found)} sticking out more than {UNCOVERED_MM:.0f} mm beyond where they join the rest (the "
            f"deepest {found[0]['depth_mm']:.0f} mm), cells on each: {cells}")


@node("layout.sensing_map", params=SensingMapParams, inputs=("mesh", "regions", "layout", "metrics"),
      outputs=("files",), sink=True, note=limbs_note)
def write_sensing_map(params: SensingMapParams, mesh: Mesh, regions: SurfaceRegions, layout: Layout,
                      metrics: dict) -> Files:
    """sensing_map.json (up axis; channel pairs -> crossing point, face, barycentrics, normal, pad),
    mesh.ply, metrics.json (the layout's metrics, the resting pose, the ingest repairs and the limbs)."""
    cells = layout.cells
    channels = {"tx": list(zip(layout.tx_source.tolist(), layout.tx.lengths_mm.tolist())),
                "rx": list(zip(layout.rx_source.tolist(), layout.rx.lengths_mm.tolist()))}
    files = sensing_map_files(mesh.vertices, mesh.faces, regions.up, cells.curve_a, cells.curve_b, cells.points,
                              cells.faces, cells.bary, layout.pad, channels, regions.touch_faces,
                              design=layout.design_values())
    found = limbs(mesh.vertices, mesh.faces, regions.base_distance_mm, regions.sensing_faces, cells.faces)
    return Files({**files, "metrics.json": metrics_json(metrics, pose_summary(regions), regions.touch, mesh.repairs, found)})


def pose_summary(regions: SurfaceRegions) -> dict:
    """The resting pose the layout was made for, as metrics.json reports it."""
    return {"kind": regions.pose_kind, "reason": regions.pose_reason, "up": [float(v) for v in regions.up],
            "tipping_angle_deg": regions.tipping_angle_deg, "base_area_fraction": regions.base_area_fraction,
            "sensing_area_fraction": regions.sensing_area_fraction, "tx_pole": regions.tx_pole}

