"""``curves.ring_levels``: the harmonic radial function around the Tx pole and the levels of the Rx rings.

Shared by every branch of the ring family (``curves.trace_rings`` walks the rings and their legs
per corridor) and the helices: ``u`` is 0 on the far exclusion around the Tx pole, 1 on the base and
its exclusion, harmonic in between (:mod:`retrotouch.nodes.curves.rings` says why its level sets
make rings). The *per-line climb* (:func:`line_climb`) is 0 and 1 where ``u`` is and grows along
every Tx line at one over that line's own length: where ``u`` is flat in a dead end, the Tx lines
are hairpins in and out of it, and the climb still grows along them. The branches with
``climb="per_line"`` take their rings as its level sets and their helices' ``rho`` as the climb.
For either function, ``n_rings - n_reseeded`` levels are spread so that, along the Tx lines (median
over the candidates), neighbouring rings are equally far apart from the pole to the base
(``level_spacing="area"``: so that the bands between them have equal area, fewer rings near the
pole, where the Tx lines crowd); the others pass through the points farthest from the rings before
them, which lie in dead ends (a second ear) where ``u`` barely changes and its level set makes a
long hairpin. Units: mm.
"""
from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np
from pydantic import Field

from ...graph.errors import UserError
from ...graph.node import NodeParams, node
from ..data.types import CurveSet, Mesh
from ..geometry.harmonic import harmonic_interpolation
from ..geometry.mesh_tables import MeshTables, build_tables
from ..geometry.sparse_spd import spd_solve
from .connection import DirectionField
from .rx_seeding import zero_set

LEVEL_GRID = 257
"""Levels of ``u`` at which the Tx lines' arrival distances are measured."""

RESEED_POINTS = 20000
"""Most sensing vertices the reseeding's farthest-point search measures (:func:`reseeded_levels`)."""

POLE_START = 0.05
"""A Tx candidate whose first point has ``u`` at most this starts at the pole's exclusion (:func:`line_climb`)."""

ACROSS_WEIGHT = 0.05
"""Weight of a function's change across the Tx lines against along them (:func:`along_energy`)."""


class RingLevelsParams(NodeParams):
    n_rings: int = Field(16, ge=1, description="Rx ring candidates, each with its leg in the corridor")
    n_reseeded: int = Field(4, ge=0, description="of those, rings through the points farthest from the others (dead ends)")
    level_spacing: Literal["tx_arc", "area"] = Field(
        "tx_arc", description="the other rings equally far apart along the Tx lines, or bands of equal area between them")


@dataclasses.dataclass(frozen=True)
class RingLevels:
    """The radial functions and the rings' levels: ``values`` (n_vertices,) ``u`` per vertex, ``levels``
    decreasing (fewer than ``count`` when reseeding runs out of dead ends), ``count`` the rings asked
    for (at most one per Tx candidate); ``climb`` (n_vertices,) the per-line climb
    (:func:`line_climb`) and ``climb_levels`` its rings' levels, spread and reseeded the same way."""

    values: np.ndarray
    levels: np.ndarray
    count: int
    climb: np.ndarray
    climb_levels: np.ndarray

    def function(self, climb: str) -> tuple[np.ndarray, np.ndarray]:
        """(values per vertex, levels) of the rings of ``climb``: ``"median"`` (``u``) or ``"per_line"``."""
        return (self.climb, self.climb_levels) if climb == "per_line" else (self.values, self.levels)


def row_values(tables: MeshTables, vertex_values: np.ndarray, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Piecewise-linear vertex values at surface points (face, barycentrics)."""
    return np.einsum("kc,kc->k", vertex_values[tables.faces[faces]], bary)


def radial_function(tables: MeshTables, regions, pole: int) -> np.ndarray:
    """``(n,)`` the harmonic radial function ``u``: 0 on the far exclusion's vertices and the pole,
    1 on the vertices of the base and its exclusion, harmonic elsewhere (see the module docstring)."""
    inner = np.union1d(tables.faces[np.asarray(regions.exclusion_far, dtype=bool)].ravel(), [pole])
    outer_faces = np.asarray(regions.base_faces, dtype=bool) | np.asarray(regions.exclusion_base, dtype=bool)
    outer = np.setdiff1d(np.unique(tables.faces[outer_faces]), inner)
    fixed = np.r_[inner, outer]
    values = np.r_[np.zeros(len(inner)), np.ones(len(outer))]
    return harmonic_interpolation(tables.vertices, tables.faces, fixed, values)


def tx_arc_profile(tx: CurveSet, u_rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(``LEVEL_GRID`` levels of ``u`` from 0 to 1, the median over the Tx candidates of the arc length
    (mm) at which a line first reaches each level, made non-decreasing). ``u_rows``: ``u`` at every
    row of ``tx``."""
    grid = np.linspace(0.0, 1.0, LEVEL_GRID)
    arrival = np.empty((tx.count, len(grid)))
    for c in range(tx.count):
        rows = tx.curve(c)
        arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(tx.points[rows], axis=0), axis=1))]
        reached, first = np.unique(np.maximum.accumulate(u_rows[rows]), return_index=True)
        arrival[c] = np.interp(grid, reached, arc[first]) if len(reached) > 1 else arc[-1]
    return grid, np.maximum.accumulate(np.median(arrival, axis=0))


def tx_arc_levels(tx: CurveSet, u_rows: np.ndarray, n: int) -> np.ndarray:
    """``n`` levels of ``u`` in decreasing order, spread in equal steps of the distance along the Tx
    lines (where the crossings of one Tx line follow each other, :func:`tx_arc_profile`) from the
    pole to the base, half a step from either end."""
    grid, along = tx_arc_profile(tx, u_rows)
    targets = along[0] + (np.arange(n)[::-1] + 0.5) / n * (along[-1] - along[0])
    return np.interp(targets, along, grid)


class LevelSets:
    """The chained level sets (:func:`zero_set`) of piecewise-linear vertex ``values`` inside the
    ``sensing`` faces, each level computed once: ``level_sets(c)`` is ``values = c``."""

    def __init__(self, tables: MeshTables, values: np.ndarray, sensing: np.ndarray):
        self.tables, self.values, self.sensing, self.cache = tables, values, sensing, {}

    def __call__(self, level: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        key = float(level)
        if key not in self.cache:
            self.cache[key] = zero_set(self.tables, self.values - key, self.sensing)
        return self.cache[key]


def area_levels(tables: MeshTables, u: np.ndarray, sensing: np.ndarray, n: int) -> np.ndarray:
    """``n`` levels of ``u`` in decreasing order that cut the sensing region into bands of equal area
    (mm^2, faces at their mean ``u``), half a band from either end: a ring near the pole, where the Tx
    lines crowd, gets as much surface around it as one near the base. Faces where ``u`` is 1 at every
    corner (enclosed by the base, where no ring reaches) are left out."""
    face_u = u[tables.faces[sensing]].mean(axis=1)
    reachable = face_u < 1.0 - 1e-9
    order = np.argsort(face_u[reachable])
    cumulative = np.cumsum(tables.areas[sensing][reachable][order])
    targets = (np.arange(n)[::-1] + 0.5) / n * cumulative[-1]
    return np.interp(targets, cumulative, face_u[reachable][order])


def reseeded_levels(u_sets: LevelSets, levels: np.ndarray, count: int) -> np.ndarray:
    """``levels`` and ``count`` more, each the level through the sensing vertex farthest (mm, to the
    level sets' polylines) from the rings so far, in decreasing order: a dead end such as an ear, where
    ``u`` barely changes, falls between two evenly spread levels and gets a ring of its own. On a mesh
    with more than ``RESEED_POINTS`` sensing vertices, every k-th of them is measured (at most
    ``RESEED_POINTS``): a farthest point needs no finer sampling than the default mesh's."""
    tables, u = u_sets.tables, u_sets.values
    vertices = np.unique(tables.faces[u_sets.sensing])
    vertices = vertices[:: -(-len(vertices) // RESEED_POINTS)]
    chosen = list(levels)
    nearest = level_distance(u_sets, chosen, tables.vertices[vertices])
    for _ in range(count):
        level = float(u[vertices[np.argmax(nearest)]])
        if not 0.0 < level < 1.0:
            break
        chosen.append(level)
        nearest = np.minimum(nearest, level_distance(u_sets, [level], tables.vertices[vertices]))
    return np.sort(np.asarray(chosen))[::-1]


def level_distance(u_sets: LevelSets, levels: list[float], points: np.ndarray) -> np.ndarray:
    """Distance (mm) of ``points`` from the nearest of the level sets ``u = level`` for ``levels``
    (inf if they are all empty)."""
    from scipy.spatial import cKDTree

    ends = [np.vstack([p, q]) for _, p, q in (u_sets(level) for level in levels) if len(p)]
    if not ends:
        return np.full(len(points), np.inf)
    return cKDTree(np.vstack(ends)).query(points)[0]


def between_faces(tables: MeshTables, u: np.ndarray) -> np.ndarray:
    """``(m,)`` the faces between the pole's exclusion (``u = 0``) and the base (``u = 1``)."""
    face_u = u[tables.faces]
    return (face_u.max(axis=1) > 0.0) & (face_u.min(axis=1) < 1.0)


def along_energy(tables: MeshTables, idx: np.ndarray, direction: np.ndarray):
    """(``G`` (3k, n) the gradient of vertex values on the faces ``idx``, ``D`` (3k, 3k) the
    area-weighted norm ``|direction . g| ^ 2 + ACROSS_WEIGHT |g| ^ 2`` of a gradient ``g`` there),
    scipy CSR: the energy of :func:`line_climb` and :func:`.helices.winding_angle` is ``(G f - t)^T D (G f - t)``."""
    import scipy.sparse as sp

    k, n = len(idx), len(tables.vertices)
    grads = tables.bary_gradients[idx]  # (k, 3 corners, 3 xyz)
    rows = (3 * np.arange(k)[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1)
    cols = np.broadcast_to(tables.faces[idx][:, :, None], rows.shape)
    G = sp.csr_matrix((grads.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * k, n))
    X = direction[idx]
    blocks = tables.areas[idx][:, None, None] * (X[:, :, None] * X[:, None, :] + ACROSS_WEIGHT * np.eye(3))
    block_rows = (3 * np.arange(k)[:, None, None] + np.arange(3)[None, :, None]).repeat(3, axis=2)
    D = sp.csr_matrix((blocks.ravel(), (block_rows.ravel(), np.swapaxes(block_rows, 1, 2).ravel())), shape=(3 * k, 3 * k))
    return G, D


def line_climb(tables: MeshTables, u: np.ndarray, tx: CurveSet, direction: np.ndarray) -> np.ndarray:
    """``(n,)`` the per-line climb ``rho``: 0 where ``u`` is 0, 1 where it is 1, and in between the
    least energy ``sum area ((X . grad rho - g) ^ 2 + ACROSS_WEIGHT |grad rho - g X| ^ 2)``, ``X``
    (m, 3) the Tx lines' unit direction per face and ``g`` (1/mm) one over the length of the Tx
    candidates through the face that start at the pole's exclusion (their mean; the nearest such
    face's elsewhere: a line reseeded from a free end climbs only part of the way), clipped to [0, 1]."""
    from scipy.spatial import cKDTree

    faces = tables.faces
    total, count = np.zeros(len(faces)), np.zeros(len(faces))
    starts = tx.offsets[:-1]
    whole = np.repeat(row_values(tables, u, tx.faces[starts], tx.bary[starts]) <= POLE_START, np.diff(tx.offsets))
    np.add.at(total, tx.faces[whole], np.repeat(1.0 / np.maximum(tx.lengths_mm, 1e-9), np.diff(tx.offsets))[whole])
    np.add.at(count, tx.faces[whole], 1.0)
    crossed = count > 0
    centroids = tables.vertices[faces].mean(axis=1)
    slope = np.empty(len(faces))
    slope[crossed] = total[crossed] / count[crossed]
    slope[~crossed] = slope[crossed][cKDTree(centroids[crossed]).query(centroids[~crossed])[1]]
    idx = np.flatnonzero(between_faces(tables, u))
    G, D = along_energy(tables, idx, direction)
    K = (G.T @ D @ G).tocsr()
    rho = np.clip(u, 0.0, 1.0)
    fixed = np.ones(len(u), dtype=bool)
    fixed[np.unique(faces[idx])] = False
    fixed |= (u <= 0.0) | (u >= 1.0)
    rhs = G.T @ (D @ (slope[idx][:, None] * direction[idx]).ravel()) - K[:, fixed] @ rho[fixed]
    rho[~fixed] = spd_solve(K[~fixed][:, ~fixed], rhs[~fixed])
    return np.clip(rho, 0.0, 1.0)


@node("curves.ring_levels", params=RingLevelsParams, inputs=("mesh", "regions", "field", "tx"), outputs=("levels",))
def ring_levels(params: RingLevelsParams, mesh: Mesh, regions, field: DirectionField, tx: CurveSet) -> RingLevels:
    """The radial functions from the Tx pole and the rings' levels (see the module docstring)."""
    if field.layer != "tx":
        raise UserError(f"curves.ring_levels needs the tx field (distance from the Tx pole), got the {field.layer} field")
    tables = build_tables(mesh.vertices, mesh.faces)
    u = radial_function(tables, regions, field.start_vertex)
    sensing = np.asarray(regions.sensing_faces, dtype=bool)
    n = min(params.n_rings, tx.count)
    n_even = max(n - params.n_reseeded, 1)
    climb = line_climb(tables, u, tx, field.face_direction)
    spread = []
    for values in (u, climb):
        if params.level_spacing == "tx_arc":
            even = tx_arc_levels(tx, row_values(tables, values, tx.faces, tx.bary), n_even)
        else:
            even = area_levels(tables, values, sensing, n_even)
        spread.append(reseeded_levels(LevelSets(tables, values, sensing), even, n - n_even))
    return RingLevels(u, spread[0], n, climb, spread[1])
