"""Layout quality metrics (paper Table 1): Voronoi uniformity of the pads and friends, and a branch's figures.

Coverage, uncovered spots and Voronoi cells are over the touchable sensing faces (``samples.touch_faces``),
and the vertices' coverage and uncovered share over the whole sensing region too (``sensing_region``);
same-layer clearance is over the whole sensing region, where traces run.

Voronoi CV: every touchable sensing face is assigned to the pad geodesically nearest to its centroid (the
centroid value of the P1-interpolated heat-method distance field of each pad); the cell area of a
pad is the summed area of its faces; CV = population std / mean of the cell areas (0 for a perfectly
regular layout). Uncovered spots: the connected pieces of the sensing region whose vertices lie
farther than ``UNCOVERED_MM`` (geodesic) from every cell, where a touch reaches few crossings and its
position is poorly determined. Limbs: the dead ends of the geodesic distance from the base deeper than
``UNCOVERED_MM`` (:mod:`retrotouch.nodes.geometry.dead_ends`: legs, arms, ears, horns, a tail) that hold
sensing faces, each with the cells on it. Distances and lengths in mm, areas in mm^2.
"""
from __future__ import annotations

import numpy as np

from ..data.types import Layout, Mesh
from ..geometry.dead_ends import dead_end_vertices, dead_ends, mesh_edges
from ..geometry.triangles import areas, corners, vertex_areas
from .clearance import clearance_profile, walls_for
from .problem import SelectionProblem
from .samples import SurfaceSamples
from .selection import SelectionResult


_ROWS_PER_BLOCK = 4096  # faces or vertices per block of the (rows, pads) reductions below

UNCOVERED_MM = 10.0
"""A sensing point farther than this (geodesic, mm) from every cell is uncovered: a finger touching there
is more than a finger's width (9 mm) from the nearest crossing."""

UNCOVERED_SPOTS_LISTED = 5
"""Uncovered spots listed in the metrics, largest first."""


def voronoi_cell_areas(
    pad_fields: np.ndarray, vertices: np.ndarray, faces: np.ndarray, face_mask: np.ndarray
) -> np.ndarray:
    """Cell area (mm^2) per pad; ``pad_fields`` (n_vertices, P) are the pads' distance fields."""
    P = pad_fields.shape[1]
    idx = np.flatnonzero(face_mask)
    owner = np.empty(len(idx), dtype=np.int64)
    for start in range(0, len(idx), _ROWS_PER_BLOCK):  # a (block, 3, P) gather at a time, not (m_s, 3, P)
        block = slice(start, start + _ROWS_PER_BLOCK)
        owner[block] = np.argmin(pad_fields[faces[idx[block]]].mean(axis=1), axis=1)
    return np.bincount(owner, weights=areas(corners(vertices, faces[idx])), minlength=P)


def row_minima(fields: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """The smallest value in each of the ``rows`` of ``fields`` (n, P), by blocks of rows."""
    return np.concatenate([fields[rows[start:start + _ROWS_PER_BLOCK]].min(axis=1)
                           for start in range(0, len(rows), _ROWS_PER_BLOCK)])


def uncovered_spots(nearest_mm: np.ndarray, vertices: np.ndarray, faces: np.ndarray, face_mask: np.ndarray,
                    threshold_mm: float = UNCOVERED_MM) -> dict:
    """The share of the ``face_mask`` region's area farther than ``threshold_mm`` from every cell and its
    spots, largest first (at most ``UNCOVERED_SPOTS_LISTED``): area, largest distance, farthest point.
    ``nearest_mm`` (n_vertices,) is each vertex's distance to its nearest cell (only the region's are
    read). A vertex stands for a third of the area of the region's faces around it; a spot is a set of
    uncovered vertices joined by edges of those faces."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    region = np.asarray(faces)[np.asarray(face_mask, dtype=bool)]
    vertex_area = vertex_areas(vertices, region)
    uncovered = np.zeros(len(vertices), dtype=bool)
    inside = np.unique(region)
    uncovered[inside] = nearest_mm[inside] > threshold_mm
    edges = np.concatenate([region[:, [0, 1]], region[:, [1, 2]], region[:, [2, 0]]])
    edges = edges[uncovered[edges].all(axis=1)]
    n = len(vertices)
    _, label = connected_components(coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n)),
                                    directed=False)
    members = np.flatnonzero(uncovered)
    spot_area = np.bincount(label[members], weights=vertex_area[members], minlength=n)
    labels = np.unique(label[members])
    spots = []
    for spot in labels[np.argsort(-spot_area[labels])][:UNCOVERED_SPOTS_LISTED]:
        own = members[label[members] == spot]
        far = own[np.argmax(nearest_mm[own])]
        spots.append({"area_mm2": float(spot_area[spot]), "max_distance_mm": float(nearest_mm[far]),
                      "point": [float(x) for x in vertices[far]]})
    return {"uncovered_threshold_mm": float(threshold_mm),
            "uncovered_share": float(vertex_area[members].sum() / vertex_area.sum()), "uncovered_spots": spots}


def limbs(vertices: np.ndarray, faces: np.ndarray, base_distance_mm: np.ndarray, sensing_faces: np.ndarray,
          cell_faces: np.ndarray) -> list[dict]:
    """The object's limbs that sense (module docstring; a limb inside the base, a foot, is left out), deepest
    first: tip point, depth, sensing area (a limb's own limbs included) and how many of the cells (on
    ``cell_faces``) lie on it."""
    edges = mesh_edges(faces)
    sensing_area = np.where(sensing_faces, areas(corners(vertices, faces)), 0.0)
    out = []
    for end in dead_ends(base_distance_mm, edges, UNCOVERED_MM):
        on_limb = dead_end_vertices(base_distance_mm, edges, end)[faces].all(axis=1)
        if sensing_area[on_limb].sum() > 0.0:
            out.append({"tip": [float(x) for x in vertices[end.tip]], "depth_mm": end.depth,
                        "area_mm2": float(sensing_area[on_limb].sum()), "cells": int(on_limb[cell_faces].sum())})
    return out


def coefficient_of_variation(values: np.ndarray) -> float:
    """Population standard deviation over mean."""
    values = np.asarray(values, dtype=np.float64)
    return float(values.std() / values.mean())


def min_pairwise(distance_mm: np.ndarray) -> float:
    """Smallest off-diagonal entry of a symmetric distance matrix (inf for fewer than 2 points)."""
    if len(distance_mm) < 2:
        return float("inf")
    return float(distance_mm[np.triu_indices(len(distance_mm), k=1)].min())


def phase1_summary(report: dict) -> dict:
    """Phase 1's worst stage gap on the model's objectives (radius; sum of level**p), the same in mm
    (radius; power mean), the worst gap against the bounds valid without the trust region
    (``global_gap``), the solver, and every stage's objective and bound (mm)."""
    stages = report.get("stages", [])

    def worst(key: str, fallback: str = "gap"):
        values = [st.get(key, st[fallback]) for st in stages]
        return None if not stages or any(v is None for v in values) else max(values)

    return {"gap": worst("gap"), "gap_mm": worst("gap_power_mean_mm"), "global_gap": worst("global_gap"),
            "solver": report.get("solver"),
            "stages": [{"stage": st["stage"], "status": st["status"], "objective": st["objective"], "bound": st["bound"],
                        "gap": st["gap"]} for st in stages]}


def layout_metrics(mesh: Mesh, samples: SurfaceSamples, problem: SelectionProblem, selection: SelectionResult, layout: Layout,
                   cell_fields: np.ndarray, pad_distance: np.ndarray, cells: np.ndarray, channel_pairs: int, power: int) -> dict:
    """Quality figures of a branch's layout: coverage, Voronoi CV over all crossings and over the
    pads, cells out of the ``channel_pairs`` available, same-layer clearance on the traces' centre lines;
    ``cell_fields`` are the cells' distance fields, ``cells`` the candidate crossings that became cells and
    ``power`` the secondary objective's."""
    tx_sel, rx_sel, pad = layout.tx_source, layout.rx_source, layout.pad
    nearest = problem.distance[:, cells].min(axis=1)
    sensing_vertices = np.unique(mesh.faces[samples.sensing_faces])
    touch_vertices = np.unique(mesh.faces[samples.touch_faces])
    vertex_nearest = np.full(len(mesh.vertices), np.inf)
    vertex_nearest[sensing_vertices] = row_minima(cell_fields, sensing_vertices)
    cell_area = voronoi_cell_areas(cell_fields[:, pad], mesh.vertices, mesh.faces, samples.touch_faces)
    all_area = voronoi_cell_areas(cell_fields, mesh.vertices, mesh.faces, samples.touch_faces)
    tx_lengths, rx_lengths = layout.tx.lengths_mm, layout.rx.lengths_mm
    bound = layout.trace_width_mm + layout.clearance_mm
    walls = walls_for(mesh, bound)
    clearance = {layer: clearance_profile(curves, samples.sensing_faces, bound, walls=walls)
                 for layer, curves in (("tx", layout.tx), ("rx", layout.rx))}
    closest = [c["min_centre_distance_mm"] for c in clearance.values() if c["min_centre_distance_mm"] is not None]
    return {
        "coverage_radius_mm": float(nearest.max()),
        "coverage_radius_vertices_mm": float(vertex_nearest[touch_vertices].max()),
        **uncovered_spots(vertex_nearest, mesh.vertices, mesh.faces, samples.touch_faces),
        "touchable_share": samples.touch_area_mm2 / samples.sensing_area_mm2,
        "sensing_region": {"coverage_radius_vertices_mm": float(vertex_nearest[sensing_vertices].max()),
                           "uncovered_share": uncovered_spots(vertex_nearest, mesh.vertices, mesh.faces,
                                                              samples.sensing_faces)["uncovered_share"]},
        "mean_distance_mm": float(nearest.mean()),
        "power_mean_distance_mm": float(np.mean(nearest**power) ** (1.0 / power)),
        "voronoi_cv": coefficient_of_variation(cell_area) if pad.sum() else None,
        "voronoi_cv_pads": coefficient_of_variation(cell_area) if pad.sum() else None,
        "voronoi_cv_all_crossings": coefficient_of_variation(all_area) if len(pad) else None,
        "voronoi_cell_area_mm2": {"mean": float(cell_area.mean()), "min": float(cell_area.min()),
                                  "max": float(cell_area.max())} if pad.sum() else None,
        "empty_crossing_cells": int(np.count_nonzero(all_area == 0.0)),
        "pads": int(pad.sum()),
        "cells": int(len(pad)),
        "channel_pairs": int(channel_pairs),
        "tx_channels": int(len(tx_sel)),
        "rx_channels": int(len(rx_sel)),
        "pad_radius_mm": layout.pad_radius_mm,
        "d_min_mm": layout.d_min_mm,
        "trace_width_mm": layout.trace_width_mm,
        "clearance_mm": layout.clearance_mm,
        "min_pad_spacing_mm": min_pairwise(pad_distance) if pad.sum() > 1 else None,
        "min_same_layer_clearance_mm": min(closest) if closest else None,
        "same_layer_clearance": clearance,
        "phase1_gap": phase1_summary(selection.report)["gap"],
        "phase1_gap_mm": phase1_summary(selection.report)["gap_mm"],
        "phase1_global_gap": phase1_summary(selection.report)["global_gap"],
        "phase1_summary": phase1_summary(selection.report),
        "curve_lengths_mm": {"tx": [float(v) for v in tx_lengths], "rx": [float(v) for v in rx_lengths],
                             "total": float(tx_lengths.sum() + rx_lengths.sum())},
        "unwired_selected_curves": {"tx": [int(a) for a in np.setdiff1d(selection.tx, tx_sel)],
                                    "rx": [int(b) for b in np.setdiff1d(selection.rx, rx_sel)]},
    }
