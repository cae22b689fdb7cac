"""Dead ends of a function over a closed mesh's vertices: the branches of the merge tree of its
superlevel sets (0-dimensional persistence).

Sweeping ``values`` from the top down, each local maximum starts a component of the superlevel set;
where two components meet (at an edge whose lower end has the value ``join``), the one with the
lower maximum ends there: a dead end, ``depth = values[tip] - join``. Its vertices are those above
``join`` connected to its tip above ``join``; a deeper dead end's vertices include those of the
shallower ones that joined it first. With the geodesic distance from an object's base, the deep
dead ends are the limbs, ears, horns and tails that stick out away from the base. Units: those of
``values`` (mm).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components


@dataclasses.dataclass(frozen=True)
class DeadEnd:
    tip: int  # vertex of the branch's maximum
    join_value: float  # where the branch meets a higher one
    depth: float  # values[tip] - join_value


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """``(E, 2)`` unique vertex pairs ``a < b`` of the faces' edges."""
    pairs = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(pairs, axis=1), axis=0)


def _merge(values: np.ndarray, edges: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Kruskal over ``edges`` in ``order`` (their lower ends' values, descending): per vertex, the
    value at which the branch whose maximum it is ends (nan: it is no maximum, or the highest)."""
    n = len(values)
    parent = np.arange(n)
    top = np.arange(n)  # the maximum of each root's component
    ends = np.full(n, np.nan)
    for k in order:
        a, b = edges[k, 0], edges[k, 1]
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        while parent[b] != b:
            parent[b] = parent[parent[b]]
            b = parent[b]
        if a == b:
            continue
        low, high = (a, b) if values[top[a]] < values[top[b]] else (b, a)
        ends[top[low]] = min(values[edges[k, 0]], values[edges[k, 1]])
        parent[low] = high
    return ends


def dead_ends(values: np.ndarray, edges: np.ndarray, min_depth: float) -> list[DeadEnd]:
    """The dead ends of vertex ``values`` deeper than ``min_depth``, deepest first; ``edges`` from
    :func:`mesh_edges`."""
    order = np.argsort(-np.minimum(values[edges[:, 0]], values[edges[:, 1]]), kind="stable")
    ends = _merge(np.asarray(values, dtype=np.float64), edges, order)
    tips = np.flatnonzero(np.isfinite(ends) & (values - np.nan_to_num(ends, nan=np.inf) > min_depth))
    found = [DeadEnd(int(t), float(ends[t]), float(values[t] - ends[t])) for t in tips]
    return sorted(found, key=lambda end: -end.depth)


def dead_end_vertices(values: np.ndarray, edges: np.ndarray, end: DeadEnd) -> np.ndarray:
    """``(n,)`` mask of the dead end's vertices (module docstring); ``edges`` from :func:`mesh_edges`."""
    above = values > end.join_value
    edges = edges[above[edges[:, 0]] & above[edges[:, 1]]]
    n = len(values)
    graph = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    return above & (labels == labels[end.tip])
