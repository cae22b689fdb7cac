"""``curves.trace_limbs``: Tx rings around the object's limbs and Rx lines out of them, added to a helix
branch's candidates.

A *limb* (a leg, an arm, a tail, a second ear) is a dead end of the distance ``d`` from the base
(:mod:`retrotouch.nodes.geometry.dead_ends`) deeper than ``min_depth_mm`` with sensing faces on it (a
foot inside the base has none). The Tx field flows from the pole to the base past it: no Tx line enters
it, so no helix crosses a Tx line there. Each limb gets crossings of its own, with the layers the other
way round from the body:

* **Tx rings** around the limb: level sets of ``d`` inside it, ``ring_spacing_mm`` apart (at most
  ``max_rings``, half a spacing from the tip and from where the limb joins the rest), whose legs run
  side by side along a *spine* (the offset legs of :mod:`.rings`, the tip taking the pole's place):
  a line from the tip down ``-grad d`` to where the limb joins the rest and on along the Tx field to
  the base. On the body a leg runs beside a Tx field line: it crosses only Tx lines that come nearer
  that line than the leg (phase 1 keeps such pairs apart), and each helix once.
* **Rx lines** out of the limb: from the tip down ``-grad d`` to where the limb joins the rest, then
  along the helix level set (``psi`` of :mod:`.helices`) through that point to the base: a helix
  there, so on the body it crosses no helix and each Tx line once; inside the limb it crosses the
  limb's rings.

Rings are oriented as Tx lines (their free start at the ring's end, the base at the leg's end), lines
as Rx curves (from the base; their free end at the tip). ``CurveSet.limb`` tells the limb each added
curve serves (-1 for the branch's own curves): phase 1 first solves the branch without them, so they
never leave its coverage radius worse (:func:`retrotouch.nodes.layout.selection.solve_radius_stage`).
Units: mm.
"""
from __future__ import annotations

import numpy as np
from pydantic import Field

from ...graph.node import NodeParams, node
from ..data.types import CurveEnd, CurveSet, Mesh
from ..geometry.dead_ends import DeadEnd, dead_end_vertices, dead_ends
from ..geometry.mesh_tables import MeshTables, build_tables
from .assembly import assemble, joined, packed_rows, polyline_rows, reversed_rows, reversed_walk
from .connection import DirectionField
from .helices import RHO_MIN, HelixChart, HelixSets
from .integrator import faces_near, trace
from .ring_levels import RingLevels, row_values
from .rings import TraceRingsParams, either_way, ring_curves, ring_walk
from .tracing import TraceTxParams, base_region_of
from .tx_seeding import fan_sectors, tx_starts, uniform_angles


class TraceLimbsParams(NodeParams):
    min_depth_mm: float = Field(10.0, ge=0, description="limbs sticking out more than this beyond where they join the "
                                "rest (mm) get rings and lines")
    ring_spacing_mm: float = Field(8.0, gt=0, description="distance between a limb's Tx rings along it (mm)")
    max_rings: int = Field(4, ge=1, description="most Tx rings around one limb")
    lines_per_limb: int = Field(4, ge=0, description="Rx line candidates out of each limb")
    spines: int = Field(8, ge=1, description="spine candidates per limb, at even angles around its tip")


def descent(tables: MeshTables, values: np.ndarray) -> np.ndarray:
    """``(m, 3)`` the unit direction of steepest descent of piecewise-linear vertex ``values`` per face."""
    grad = np.einsum("fc,fcx->fx", values[tables.faces], tables.bary_gradients)
    return -grad / np.maximum(np.linalg.norm(grad, axis=1), 1e-12)[:, None]


def limb_rings(tables: MeshTables, regions, end: DeadEnd, limb_vertices: np.ndarray, down: np.ndarray,
               field: DirectionField, params: TraceLimbsParams) -> list[tuple[np.ndarray, np.ndarray]]:
    """Rows (faces, bary) of the Tx rings around one limb, each oriented from its free end to the base."""
    d = np.asarray(regions.base_distance_mm, dtype=np.float64)
    faces = tables.faces
    base = base_region_of(regions)
    limb_faces = limb_vertices[faces].all(axis=1)
    _, _, cum = fan_sectors(tables, end.tip)
    prefix, start_faces, start_bary = tx_starts(tables, end.tip, uniform_angles(cum[-1], params.spines))
    nothing = np.zeros(len(faces), dtype=bool)
    along = np.where(limb_faces[:, None], down, field.face_direction)
    tracing = TraceTxParams()  # as the Tx lines are traced by default
    singular = faces_near(tables, field.stop_distance, tracing.singularity_stop_mm)
    spines, _ = assemble(tables, trace(tables, along, start_faces, start_bary, nothing, base, singular, tracing.max_steps,
                                       tracing.max_face_visits, prefix), nothing, "tx", 0.0)
    # the rings' radial function: 0 at the tip, 1 on the base, flat beyond the limb (no ring leaves it)
    u = np.full(len(d), 1.0 - end.join_value / d[end.tip])
    u[limb_vertices] = 1.0 - d[limb_vertices] / d[end.tip]
    u[np.unique(faces[base])] = 1.0
    count = int(min(params.max_rings, max(1, end.depth // params.ring_spacing_mm)))
    levels = np.sort(1.0 - (end.join_value + (np.arange(count) + 0.5) / count * end.depth) / d[end.tip])[::-1]
    rows, _, _ = ring_curves(TraceRingsParams(legs="offset"), tables, regions, RingLevels(u, levels, count, u, levels), spines)
    return [reversed_rows(tables, f, b) for f, b in rows]


def limb_lines(tables: MeshTables, regions, end: DeadEnd, limb_faces: np.ndarray, down: np.ndarray, chart: HelixChart,
               helix_sets: HelixSets, count: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Rows (faces, bary) of the Rx lines out of one limb, each oriented from the base to the tip."""
    base = base_region_of(regions)
    on_base = np.zeros(len(tables.vertices), dtype=bool)
    on_base[tables.faces[base]] = True
    sensing = np.asarray(regions.sensing_faces, dtype=bool)
    _, _, cum = fan_sectors(tables, end.tip)
    prefix, start_faces, start_bary = tx_starts(tables, end.tip, uniform_angles(cum[-1], count))
    nothing = np.zeros(len(tables.faces), dtype=bool)
    tracing = TraceTxParams()
    inside, _ = assemble(tables, trace(tables, down, start_faces, start_bary, nothing, base | ~limb_faces, nothing,
                                       tracing.max_steps, tracing.max_face_visits, prefix), nothing, "rx", 0.0)
    rows = []
    for c in range(inside.count):
        part = inside.curve(c)
        points, point_faces = inside.points[part], inside.faces[part]
        joint, joint_face = points[-1], int(point_faces[-1])
        if inside.end_reason[c] != int(CurveEnd.BASE) or base[joint_face] or not sensing[joint_face]:
            continue
        bary = np.clip(tables.bary_of_points(np.array([joint_face]), joint[None]), 0.0, 1.0)
        chain = helix_sets(float(row_values(tables, chart.psi, np.array([joint_face]), bary)[0]))
        for forward in (True, False):
            walk_points, walk_faces = ring_walk(*either_way(chain, forward), joint_face, joint)
            if len(walk_points) < 2:
                continue
            rho = row_values(tables, chart.rho, walk_faces[[0, -1]], np.clip(tables.bary_of_points(walk_faces[[0, -1]],
                                                                                                 walk_points[[0, -1]]), 0, 1))
            if rho[-1] > rho[0] and on_base[tables.faces[walk_faces[-1]]].any():  # climbs to the base, not to a hole
                rows.append(polyline_rows(tables, *reversed_walk(np.vstack([points[:-1], walk_points]),
                                                                 np.r_[point_faces[:-1], walk_faces])))
                break
    return rows


def limbs_note(value: dict) -> str | None:
    """The run summary's line: how many limbs got curves (none: no line)."""
    tx, rx = value["tx"], value["rx"]
    found = len(np.unique(np.r_[tx.limb, rx.limb][np.r_[tx.limb, rx.limb] >= 0]))
    if not found:
        return None
    return (f"{found} limbs: {int((tx.limb >= 0).sum())} Tx rings around them and {int((rx.limb >= 0).sum())} Rx lines out "
            f"of them added to the candidates")


@node("curves.trace_limbs", params=TraceLimbsParams, inputs=("mesh", "regions", "chart", "tx", "tx_field", "rx"),
      outputs=("tx", "rx"), note=limbs_note)
def trace_limbs(params: TraceLimbsParams, mesh: Mesh, regions, chart: HelixChart, tx: CurveSet, tx_field: DirectionField,
                rx: CurveSet) -> dict[str, CurveSet]:
    """The helix branch's Tx candidates ``tx`` and Rx candidates ``rx`` (its helices, ``chart`` their
    coordinates) with the limbs' rings and lines after them (see the module docstring)."""
    tables = build_tables(mesh.vertices, mesh.faces)
    d = np.asarray(regions.base_distance_mm, dtype=np.float64)
    edges = tables.edges  # the mesh's unique edges, as geometry.dead_ends.mesh_edges gives them
    down = descent(tables, d)
    sensing = np.asarray(regions.sensing_faces, dtype=bool)
    helix_sets = HelixSets(tables, chart.psi, chart.period, sensing & (chart.rho[tables.faces].min(axis=1) >= RHO_MIN))
    rings, ring_limb, lines, line_limb = [], [], [], []
    for k, end in enumerate(dead_ends(d, edges, params.min_depth_mm)):
        limb_vertices = dead_end_vertices(d, edges, end)
        limb_faces = limb_vertices[tables.faces].all(axis=1)
        if not (limb_faces & sensing).any():  # inside the base (a foot)
            continue
        found = limb_rings(tables, regions, end, limb_vertices, down, tx_field, params)
        rings += found
        ring_limb += [k] * len(found)
        found = limb_lines(tables, regions, end, limb_faces, down, chart, helix_sets, params.lines_per_limb)
        lines += found
        line_limb += [k] * len(found)

    def added(own: CurveSet, rows: list, limb: list) -> CurveSet:
        extra = CurveSet(layer=own.layer, **packed_rows(tables, rows), end_reason=np.full(len(rows), int(CurveEnd.BASE), np.int8),
                         angle=own.angle, family=own.family)
        return joined(own, extra, np.asarray(limb, dtype=np.int64))

    return {"tx": added(tx, rings, ring_limb), "rx": added(rx, lines, line_limb)}
