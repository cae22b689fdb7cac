"""``curves.trace_tx`` / ``curves.trace_rx``: integral curves of a trivial-connection field.

Tracing is barycentric and exact for the piecewise-constant field
(:mod:`retrotouch.nodes.curves.integrator`); seeds come from
:mod:`retrotouch.nodes.curves.tx_seeding` and :mod:`retrotouch.nodes.curves.rx_seeding`, and the
traced rows become a ``CurveSet`` in :mod:`retrotouch.nodes.curves.assembly`.

Stops (``CurveEnd``):

* ``BASE`` when the curve enters a face of the base region (``base_faces | exclusion_base``) after
  having been outside it;
* ``SINK_EDGE`` when the field of the face across the exit edge points back at that edge (both faces
  point at their shared edge);
* ``SINGULARITY`` when it enters a face with a vertex within ``singularity_stop_mm`` (geodesic) of
  a singularity it ends at (Tx: the base centre; Rx: the dipole), after leaving its start region;
* ``LOOP`` when it enters the same face more than ``max_face_visits`` times;
* ``MAX_STEPS`` when the step budget runs out.

Families:

* **Tx** (field with +1 at the far vertex and the base centre, pointing away from the far vertex):
  with ``angle_sampling="uniform"`` (the paper), ``n_curves`` start directions at uniform intervals
  of the intrinsic angle around the far vertex (``(k + 1/2) / n`` of the cone angle, measured in the
  unfolded one-ring). Each curve goes straight from the vertex across its first face and then
  follows the field, so Tx curves are field lines and do not cross each other. The part inside
  ``exclusion_far`` is trimmed off. Uniform angles leave narrow protrusions away from the far vertex
  empty; ``angle_sampling="adaptive"`` (default) starts ``uniform_share * n_curves`` curves at
  uniform angles and then reseeds, up to ``n_curves``, field lines through the sensing points
  farthest (geodesic) from the family, a few holes per round (see :func:`adaptive_tx_traces`).
  A reseeded line is traced back against the field without sliding: it starts where it enters the
  far exclusion or, when the seed lies in the shadow of a vertex where the discrete field diverges
  (no line from the far vertex reaches it), on that diverging edge. Reseeded lines are field lines
  too, so the family still has no Tx x Tx crossings; the curves are ordered by their angle at the
  far vertex. Sensing points whose field line comes out of the base cannot be reached by Tx curves
  and stay uncovered.
* **Rx** (dipole field, pointing away from ``base_dipole[0]``): its field lines are loops that leave
  the base, run over the object and return to the base. Seeds lie on the loops' apex line, where the
  field is tangent to the geodesic circles around the dipole (zero set of ``u . grad d``, ``d`` the
  heat-method distance from ``base_dipole[0]``), inside the sensing faces, at equal arc length; the
  same seeds serve every angle. (Seeds on a geodesic ring around the dipole, as the paper
  describes, give mostly short nested loops near the base.) The traced direction in every
  face is the field rotated by ``angle_deg`` about the outward normal (counter-clockwise positive):
  the offset is relative to the field direction, and transport by the trivial connection keeps it
  constant along the curve, so the curves of one angle do not cross each other (except where
  sink-edge slides merge them). Each seed is traced both ways to the base and the halves are joined;
  the curve is oriented to start at the base, and ``end_reason`` tells how its other end stopped.

Sink edges: with ``slide_sink_edges`` (default) a curve meeting a sink edge slides along it, and
along further sink edges, to a vertex it can leave (Filippov sliding; such rows sit on vertices);
without it the curve stops there, as in the paper.

Curves that never leave their start region are dropped (counted in the stats).
"""
from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from ...graph.errors import UserError
from ...graph.node import NodeParams, node
from ..data.types import CurveSet, Mesh
from ..geometry.mesh_tables import MeshTables, build_tables
from .assembly import TraceStats, assemble, join_both_ways
from .connection import DirectionField
from .integrator import faces_near, field_direction, trace
from .rx_seeding import rx_seeds
from .tx_seeding import adaptive_tx_traces, fan_sectors, tx_traces, uniform_angles


class TraceTxParams(NodeParams):
    n_curves: int = Field(100, ge=1, description="Tx curves (at most this many with adaptive angle sampling)")
    angle_sampling: Literal["uniform", "adaptive"] = Field(
        "adaptive", description="start angles at the far vertex: uniform, or uniform then reseeded through the largest gaps"
    )
    uniform_share: float = Field(0.5, gt=0, le=1, description="adaptive: share of n_curves started at uniform angles (1: uniform)")
    singularity_stop_mm: float = Field(3.0, gt=0, description="stop within this geodesic distance (mm) of the base centre")
    max_steps: int = Field(20000, ge=1, description="face steps per family before giving up")
    max_face_visits: int = Field(3, ge=1, description="loop guard: a curve may enter a face this many times")
    slide_sink_edges: bool = Field(True, description="slide along sink edges instead of stopping there (the paper stops)")


class TraceRxParams(NodeParams):
    angle_deg: float = Field(0.0, ge=-90, le=90, description="offset of the traced direction from the field (deg, CCW)")
    n_curves: int = Field(100, ge=1, description="Rx curves per angle")
    singularity_stop_mm: float = Field(3.0, gt=0, description="stop within this geodesic distance (mm) of the dipole")
    max_steps: int = Field(20000, ge=1, description="face steps per family before giving up")
    max_face_visits: int = Field(3, ge=1, description="loop guard: a curve may enter a face this many times")
    slide_sink_edges: bool = Field(True, description="slide along sink edges instead of stopping there (the paper stops)")


def base_region_of(regions) -> np.ndarray:
    return np.asarray(regions.base_faces, dtype=bool) | np.asarray(regions.exclusion_base, dtype=bool)


def trace_tx_curves(params: TraceTxParams, tables: MeshTables, regions, field: DirectionField) -> tuple[CurveSet, TraceStats]:
    if field.layer != "tx":
        raise UserError(f"curves.trace_tx needs the tx field, got the {field.layer} field: wire curves.connection with layer: tx")
    base = base_region_of(regions)
    start_region = np.asarray(regions.exclusion_far, dtype=bool) & ~base
    singular = faces_near(tables, field.stop_distance, params.singularity_stop_mm)
    if params.angle_sampling == "uniform":
        _, _, cum = fan_sectors(tables, field.start_vertex)
        traces = tx_traces(params, tables, field, uniform_angles(cum[-1], params.n_curves), start_region, base, singular)
    else:
        traces = adaptive_tx_traces(params, tables, regions, field, start_region, base, singular)
    return assemble(tables, traces, start_region, "tx", 0.0)


def trace_rx_curves(params: TraceRxParams, tables: MeshTables, regions, field: DirectionField) -> tuple[CurveSet, TraceStats]:
    if field.layer != "rx":
        raise UserError(f"curves.trace_rx needs the rx field, got the {field.layer} field: wire curves.connection with layer: rx")
    base = base_region_of(regions)
    sensing = ~base & ~np.asarray(regions.exclusion_far, dtype=bool)
    faces, bary = rx_seeds(tables, field, sensing, params.n_curves)
    angle = float(np.radians(params.angle_deg))
    direction = field_direction(field, tables, angle)
    singular = faces_near(tables, field.stop_distance, params.singularity_stop_mm)
    nothing = np.zeros(len(tables.faces), dtype=bool)
    halves = [
        trace(
            tables, sign * direction, faces, bary, nothing, base, singular, params.max_steps, params.max_face_visits, None, params.slide_sink_edges
        )
        for sign in (-1.0, 1.0)
    ]
    return assemble(tables, join_both_ways(tables, *halves), nothing, "rx", angle)


@node("curves.trace_tx", params=TraceTxParams, inputs=("mesh", "regions", "field"), outputs=("curves", "stats"))
def trace_tx(params: TraceTxParams, mesh: Mesh, regions, field: DirectionField) -> dict[str, object]:
    """Tx curves: field lines from the far vertex (uniform angles, then reseeded into the largest gaps
    with the default ``angle_sampling="adaptive"``), trimmed at the far exclusion, ending at the base."""
    curves, stats = trace_tx_curves(params, build_tables(mesh.vertices, mesh.faces), regions, field)
    return {"curves": curves, "stats": stats}


@node("curves.trace_rx", params=TraceRxParams, inputs=("mesh", "regions", "field"), outputs=("curves", "stats"))
def trace_rx(params: TraceRxParams, mesh: Mesh, regions, field: DirectionField) -> dict[str, object]:
    """Rx curves of one angle offset: dipole loops through seeds on their apex line, from the base to the base."""
    curves, stats = trace_rx_curves(params, build_tables(mesh.vertices, mesh.faces), regions, field)
    return {"curves": curves, "stats": stats}
