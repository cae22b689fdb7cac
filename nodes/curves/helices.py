"""``curves.trace_helices``: an Rx family of helices around the Tx pole, with no corridor.

A ring around the Tx pole (:mod:`.rings`) must leave a gap for the legs of the rings inside it, so
the legs run side by side in a corridor that no Tx line may cross: a strip from the pole to the base
without a cell. A *helix* needs no leg. It starts on the base, winds once around the pole while it
climbs, and stops (a free end) short of the pole; every Tx line from the pole to the base meets it
once, and helices of different phases never meet, like the threads of a multi-start screw.

In coordinates: ``theta`` in turns [0, 1) is the angle around the pole, the function that winds
once around it and is as nearly constant along the Tx lines as it can be (:func:`winding_angle`),
growing clockwise seen from outside, looking at the pole; ``rho`` in [0, 1] climbs from the pole's
exclusion (0) to the base (1), in one of two ways (``climb``):

* ``"median"``: the radial function ``u`` of :mod:`.ring_levels` re-measured as the median distance
  along the Tx lines (:func:`.ring_levels.tx_arc_profile`). In a dead end off the pole (a second ear)
  ``u`` is flat: the Tx lines there are hairpins in and out of it, and the helices run along them;
* ``"per_line"``: the function that grows along every Tx line at one over that line's own length
  (:func:`.ring_levels.line_climb`, shared with the rings), so a hairpin through a dead end climbs
  there too and the helices cross it.

Helix ``k`` is the level set ``psi = c_k`` of the circle-valued ``psi = (rho + s P theta) mod P``,
``P = 1 - RHO_MIN``, ``s = +1`` for left-handed helices (climbing clockwise seen from the pole) and
``-1`` for right-handed ones, inside ``rho >= RHO_MIN``: one turn from the base up to ``RHO_MIN``. Along a line
of constant ``theta`` the helices' levels follow each other every ``P / n`` of ``rho``, so each Tx
line crosses all of them at heights that shift from one Tx line to the next (a sheared grid).
``grad rho`` and ``grad theta`` are nearly orthogonal and non-zero, so ``psi`` has no critical point
and each level set is one curve. ``n_helices - n_reseeded`` phases are spread evenly; the others
pass through the sensing points farthest from the helices before them (a second ear, where ``u`` and
``theta`` barely change). A helix climbs the whole way from the base to the pole in one turn, so it
runs at an angle ``atan(C / (P L))`` to the Tx lines, ``C`` the way round the pole there and ``L``
the Tx lines' length: steeply where the object is slender and near the pole. It stops where it first
runs within ``min_crossing_angle_deg`` of them over ``ALONG_MM``, leaving the crossings near the pole
to the Tx lines' crowding there (and a slender object to the rings). Units: mm; angles in turns
unless named in degrees.
"""
from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np
from pydantic import Field

from ...graph.errors import UserError
from ...graph.node import NodeParams, node
from ..data.types import CurveEnd, CurveSet, Mesh
from ..geometry.mesh_tables import MeshTables, build_tables
from ..geometry.sparse_spd import spd_solve
from .connection import DirectionField
from .ring_levels import RingLevels, along_energy, between_faces, reseeded_levels, row_values, tx_arc_profile
from .assembly import polyline_rows, reversed_walk
from .rings import pack, packed_stats
from .rx_seeding import chain_walks, zero_set

RHO_MIN = 0.02
"""Where the helices would stop near the pole, as a share of the distance from the pole's exclusion to the base."""

BASE_RHO = 0.95
"""Beyond this ``rho`` a helix is leaving the base, where the Tx lines' direction says little."""

PHASE_TOLERANCE = 1e-3
"""Reseeded phases nearer than this share of the period to another one are dropped (the same helix)."""

ALONG_MM = 10.0
"""A Tx line and a helix within a trace width of each other for this length are laid along each other."""

MIN_CROSSING_ANGLE_DEG = 8.0
"""Default ``min_crossing_angle_deg``: below the angle at which a crossing keeps a Tx line and a helix
within a trace width of each other for ``ALONG_MM`` (11.5 deg)."""


NO_HELICES = ("use the rings or dipole Rx family for this object: remove the helix nodes (winding, helices, limbs, "
              "helix_crossings, helix_select, helix_radius, helix_finish) and their entries in prescreen, screen and best "
              "from the pipeline")


class TraceHelicesParams(NodeParams):
    n_helices: int = Field(24, ge=1, description="Rx helix candidates")
    n_reseeded: int = Field(4, ge=0, description="of those, helices through the points farthest from the others (dead ends)")
    winding: Literal["left", "right"] = Field("left", description="handedness: left-handed helices climb clockwise seen from the pole")
    climb: Literal["median", "per_line"] = Field(
        "median", description="rho along the Tx lines: the median line's (from the harmonic radial function) or each line's own")
    min_crossing_angle_deg: float = Field(MIN_CROSSING_ANGLE_DEG, ge=0, lt=90,
                                          description="a helix stops where it first runs closer than this to the Tx lines over ALONG_MM (deg)")


def cut_path(tables: MeshTables, u: np.ndarray, region: np.ndarray) -> np.ndarray:
    """Shortest vertex path (indices) through the faces ``region`` from a vertex where ``u = 0`` to
    one where ``u = 1``, touching neither boundary in between."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import dijkstra

    inner, outer = u <= 0.0, u >= 1.0
    edges = tables.edges[np.isin(tables.edge_faces, np.flatnonzero(region)).any(axis=1)]
    edges = edges[~(inner | outer)[edges].all(axis=1)]
    length = np.linalg.norm(tables.vertices[edges[:, 0]] - tables.vertices[edges[:, 1]], axis=1)
    n = len(u)
    graph = sp.csr_matrix((np.r_[length, length], (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])), shape=(n, n))
    starts = np.intersect1d(np.flatnonzero(inner), edges.ravel())
    ends = np.intersect1d(np.flatnonzero(outer), edges.ravel())
    if len(starts) == 0 or len(ends) == 0:
        raise UserError(f"curves.trace_helices: the sensing region does not join the Tx pole's exclusion to the base; {NO_HELICES}")
    dist, pred = dijkstra(graph, indices=starts, min_only=True, return_predecessors=True)[:2]
    end = int(ends[np.argmin(dist[ends])])
    if not np.isfinite(dist[end]):
        raise UserError(f"curves.trace_helices: no path from the Tx pole's exclusion to the base inside the sensing region; {NO_HELICES}")
    path = [end]
    while pred[path[-1]] >= 0:
        path.append(int(pred[path[-1]]))
    return np.asarray(path[::-1], dtype=np.int64)


def winding_angle(tables: MeshTables, u: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """``(n,)`` the angle around the pole in turns [0, 1), constant along the Tx lines as far as it can
    be: on the faces between the pole's exclusion (``u = 0``) and the base (``u = 1``) the function
    that winds once around the pole (a jump of one turn across a cut from one to the other) with the
    least energy ``sum area (|direction . grad| ^ 2 + ACROSS_WEIGHT |grad| ^ 2)``, ``direction`` (m, 3)
    the Tx lines' unit direction per face; NaN elsewhere."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    faces = tables.faces
    region = between_faces(tables, u)
    path = cut_path(tables, u, region)
    on_path = np.zeros(len(u), dtype=bool)
    on_path[path] = True
    touching = region & on_path[faces].any(axis=1)
    n = len(u)
    edge_keys = tables.edges[:, 0] * n + tables.edges[:, 1]
    order = np.argsort(edge_keys)
    along_path = order[np.searchsorted(edge_keys, np.minimum(path[:-1], path[1:]) * n + np.maximum(path[:-1], path[1:]), sorter=order)]
    path_edges = np.zeros(len(tables.edges), dtype=bool)
    path_edges[along_path] = True
    a, b = tables.edge_faces[:, 0], tables.edge_faces[:, 1]
    link = touching[a] & touching[b] & ~path_edges
    m = len(faces)
    _, label = connected_components(sp.csr_matrix((np.ones(link.sum()), (a[link], b[link])), shape=(m, m)), directed=False)
    first = along_path[0]
    left = tables.edge_faces[first, 0] if tables.edges[first, 0] == path[0] else tables.edge_faces[first, 1]
    plus = touching & (label == label[left])  # faces that see the cut's vertices one turn on
    idx = np.flatnonzero(region)
    G, D = along_energy(tables, idx, direction)
    jump = (tables.bary_gradients[idx] * (plus[idx][:, None] & on_path[faces[idx]])[:, :, None]).sum(axis=1).ravel()
    K = (G.T @ D @ G).tocsr()
    rhs = -(G.T @ (D @ jump))
    free = np.zeros(n, dtype=bool)
    free[np.unique(faces[idx])] = True
    free[path[0]] = False  # the angle is defined up to a constant: 0 at the cut's first vertex
    # only the piece of the region the cut runs through winds round the pole: pieces of it that touch
    # neither (an island between the pole's exclusion and the base) keep NaN
    free_vertices = np.flatnonzero(free)
    _, piece = connected_components(K[free_vertices][:, free_vertices], directed=False)
    beside_pin = np.searchsorted(free_vertices, np.intersect1d(K[path[0]].indices, free_vertices))
    anchored = np.zeros(n, dtype=bool)
    anchored[free_vertices] = np.isin(piece, piece[beside_pin])
    theta = np.full(n, np.nan)
    theta[path[0]] = 0.0
    theta[anchored] = spd_solve(K[anchored][:, anchored], rhs[anchored])
    return np.mod(theta, 1.0)


class HelixSets:
    """Level sets of the circle-valued ``values`` (period ``period``) inside ``sensing``: ``sets(c)``
    is ``values = c`` as :func:`zero_set` chains, each level computed once. A face where the values
    wrap round (spread over more than half a period) or are NaN holds no segment."""

    def __init__(self, tables: MeshTables, values: np.ndarray, period: float, sensing: np.ndarray):
        self.tables, self.values, self.period, self.sensing, self.cache = tables, values, period, sensing, {}

    def __call__(self, level: float):
        key = float(level)
        if key not in self.cache:
            shifted = np.mod(self.values - key + 0.5 * self.period, self.period) - 0.5 * self.period
            spread = np.ptp(shifted[self.tables.faces], axis=1)
            self.cache[key] = zero_set(self.tables, shifted, self.sensing & (spread < 0.5 * self.period))
        return self.cache[key]


def longest_chain(tables: MeshTables, rho: np.ndarray, chain) -> tuple[np.ndarray, np.ndarray] | None:
    """The longest run of joined segments of a :func:`zero_set` chain, from its end nearer the base:
    (points (n, 3), face of the segment each starts), or None if it is empty."""
    walks = chain_walks(chain)
    if not walks:
        return None
    points, point_faces = max(walks, key=lambda walk: np.linalg.norm(np.diff(walk[0], axis=0), axis=1).sum())
    rho_ends = row_values(tables, rho, point_faces[[0, -1]], np.clip(tables.bary_of_points(point_faces[[0, -1]], points[[0, -1]]), 0, 1))
    return reversed_walk(points, point_faces) if rho_ends[0] < rho_ends[-1] else (points, point_faces)


def steep_index(points: np.ndarray, faces: np.ndarray, rho_points: np.ndarray, direction: np.ndarray,
                min_angle_deg: float) -> int:
    """Rows of a helix walked from the base to keep: up to the first segment off the base (``rho`` <
    ``BASE_RHO`` at both ends) where the helix, over the ``ALONG_MM`` centred on it, runs within
    ``min_angle_deg`` of ``direction`` (the Tx lines' unit direction per face) on average (the mean of
    ``|cos|`` weighted by length): beyond, it would cross them at a glancing angle and crowd the other
    helices. One face's segment alone says little: it may cross that face's direction at any angle."""
    segment = np.diff(points, axis=0)
    length = np.linalg.norm(segment, axis=1)
    along = np.r_[0.0, np.cumsum(length)]
    aligned = np.r_[0.0, np.cumsum(np.abs(np.einsum("ij,ij->i", segment, direction[faces[:-1]])))]
    middle = 0.5 * (along[:-1] + along[1:])
    lo = np.maximum(middle - 0.5 * ALONG_MM, 0.0)
    hi = np.minimum(middle + 0.5 * ALONG_MM, along[-1])
    mean_cos = (np.interp(hi, along, aligned) - np.interp(lo, along, aligned)) / np.maximum(hi - lo, 1e-12)
    off_base = np.maximum(rho_points[:-1], rho_points[1:]) < BASE_RHO
    steep = np.flatnonzero((mean_cos > np.cos(np.radians(min_angle_deg))) & (length > 0) & off_base)
    return int(steep[0]) + 1 if len(steep) else len(points)


@node("curves.winding_angle", inputs=("mesh", "levels", "field"), outputs=("theta",))
def winding_angle_node(params: NodeParams, mesh: Mesh, levels: RingLevels, field: DirectionField) -> np.ndarray:
    """:func:`winding_angle` per vertex (turns) around the Tx pole of ``field``, shared by every helix branch."""
    return winding_angle(build_tables(mesh.vertices, mesh.faces), levels.values, field.face_direction)


@dataclasses.dataclass(frozen=True)
class HelixChart:
    """The helices' coordinates (module docstring): ``rho`` (n_vertices,) the climb in [0, 1], ``psi``
    (n_vertices,) the circle-valued helix function (NaN where the winding angle is), ``period`` its period."""

    rho: np.ndarray
    psi: np.ndarray
    period: float


def helix_function(tables: MeshTables, levels: RingLevels, theta: np.ndarray, tx: CurveSet, winding: str,
                   climb: str) -> HelixChart:
    """:class:`HelixChart` of the module docstring from the winding angle ``theta`` (:func:`winding_angle`);
    ``psi`` is NaN where ``theta`` is (:class:`HelixSets` leaves those faces out)."""
    u = levels.values
    if climb == "per_line":
        rho = levels.climb
    else:
        grid, along = tx_arc_profile(tx, row_values(tables, u, tx.faces, tx.bary))
        rho = np.interp(u, grid, (along - along[0]) / max(along[-1] - along[0], 1e-12))
    period = 1.0 - RHO_MIN
    sense = 1.0 if winding == "left" else -1.0
    psi = np.mod(rho + sense * period * theta, period)  # NaN off the faces between the pole's exclusion and the base
    return HelixChart(rho, psi, period)


@node("curves.trace_helices", params=TraceHelicesParams, inputs=("mesh", "regions", "levels", "winding", "tx", "tx_field"),
      outputs=("curves", "stats", "chart"))
def trace_helices(params: TraceHelicesParams, mesh: Mesh, regions, levels: RingLevels, winding: np.ndarray, tx: CurveSet,
                  tx_field: DirectionField) -> dict[str, object]:
    """Rx helices around the Tx pole (see the module docstring); ``levels`` gives the radial functions,
    ``winding`` the angle around the pole (``curves.winding_angle``)."""
    tables = build_tables(mesh.vertices, mesh.faces)
    direction = tx_field.face_direction
    chart = helix_function(tables, levels, winding, tx, params.winding, params.climb)
    rho, psi, period = chart.rho, chart.psi, chart.period
    sensing = np.asarray(regions.sensing_faces, dtype=bool) & (rho[tables.faces].min(axis=1) >= RHO_MIN)
    sets = HelixSets(tables, psi, period, sensing)
    n_even = max(params.n_helices - params.n_reseeded, 1)
    phases = reseeded_levels(sets, (np.arange(n_even) + 0.5) / n_even * period, params.n_helices - n_even)
    phases = phases[np.r_[True, np.abs(np.diff(phases)) > PHASE_TOLERANCE * period]]
    rows, ends = [], []
    for phase in phases:
        walk = longest_chain(tables, rho, sets(phase))
        if walk is None or len(walk[0]) < 2:
            continue
        points, faces = walk
        rho_points = row_values(tables, rho, faces, np.clip(tables.bary_of_points(faces, points), 0.0, 1.0))
        keep = steep_index(points, faces, rho_points, direction, params.min_crossing_angle_deg)
        points, faces = points[:keep], faces[:keep]
        if len(points) < 2:
            continue
        rows.append(polyline_rows(tables, points, faces))
        ends.append(int(CurveEnd.BASE))
    curves = pack(tables, rows, np.asarray(ends, dtype=np.int8), 0.0 if params.winding == "left" else np.pi,
                  "helices" if params.climb == "median" else "helices_per_line")
    return {"curves": curves, "stats": packed_stats(curves, params.n_helices), "chart": chart}
