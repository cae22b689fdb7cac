"""Where an evaluation touches the object: locations spread over the sensing surface, marked by the
user (``--locations FILE``), or (for comparison with earlier figures) chosen near the crossings.

* ``"spread"`` (default): farthest-point sampling (fixed seed) of points drawn uniformly over the
  sensing region of the sensing map (``regions.detect``'s sensing faces), so they are spread over
  the surface a user would touch, whatever the crossings do.
* ``"surrounded"`` / ``"near"``: candidates around crossings (:meth:`.scripts.ScriptBuilder.location`),
  kept when the crossings within two coupling widths enclose them (``"surrounded"``) or all of them.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import Delaunay, QhullError, cKDTree

from ...graph.errors import UserError
from ..data.board import default_coupling_width_mm
from ..data.sensing_map import SensingMap
from ..geometry.surface import SurfaceProjector, farthest_point_sampling
from ..geometry.triangles import corners, normals
from .scripts import ScriptBuilder
from .virtual_board import BoardParams


def spread_locations(sensing_map: SensingMap, count: int, seed: int = 0) -> np.ndarray:
    """``count`` points (mm) on the sensing region, farthest-point sampled from ``200 x count``
    points drawn uniformly (by area) over its faces."""
    faces = np.flatnonzero(sensing_map.sensing_faces)
    if len(faces) == 0:
        raise UserError(f"sensing map {sensing_map.source} has an empty sensing region: re-run the pipeline")
    triangles = corners(sensing_map.vertices, sensing_map.faces[faces])
    area = normals(triangles)[1]
    rng = np.random.default_rng(seed)
    chosen = rng.choice(len(faces), size=200 * count, p=area / area.sum())
    u, v = rng.random((2, len(chosen)))
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    tri = triangles[chosen]
    samples = tri[:, 0] + u[:, None] * (tri[:, 1] - tri[:, 0]) + v[:, None] * (tri[:, 2] - tri[:, 0])
    return samples[farthest_point_sampling(samples, count, seed)]


def load_locations(path: str | Path, sensing_map: SensingMap) -> np.ndarray:
    """A JSON list of points ``[[x, y, z], ...]`` (mm, on the object, as marked on the real one),
    projected onto the surface; one-line UserError when missing, malformed or far from the object."""
    path = Path(path)
    example = "write a JSON list of points in mm, e.g. [[12.5, 40.0, 3.2], ...]"
    if not path.is_file():
        raise UserError(f"locations file {path} not found: {example}")
    try:
        points = np.array(json.loads(path.read_text(encoding="utf-8")), dtype=np.float64)
    except (UnicodeDecodeError, json.JSONDecodeError, TypeError, ValueError) as exc:
        raise UserError(f"locations file {path} is not a JSON list of points ({type(exc).__name__}): {example}") from None
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0 or not np.isfinite(points).all():
        raise UserError(f"locations file {path} holds no list of [x, y, z] points: {example}")
    projected = SurfaceProjector(sensing_map.vertices, sensing_map.faces).project(points)[0]
    far = np.linalg.norm(projected - points, axis=1)
    if far.max() > 5.0:
        k = int(np.argmax(far))
        raise UserError(f"locations file {path}: point {k} {points[k].tolist()} is {far[k]:.1f} mm from the object: "
                        "give points on its surface in the layout's millimetres")
    return projected


def nearest_crossing_mm(sensing_map: SensingMap, points: np.ndarray) -> np.ndarray:
    """(n,) distance (mm) from each point to the nearest crossing of the map."""
    return cKDTree(sensing_map.cell_points).query(np.atleast_2d(points))[0]


def surrounded(sensing_map: SensingMap, points: np.ndarray, reach: float) -> np.ndarray:
    """Whether each surface point (n, 3) lies inside the convex hull, in its tangent plane, of the
    crossings within ``reach`` (mm) of it (at least three, not all collinear)."""
    projector = SurfaceProjector(sensing_map.vertices, sensing_map.faces)
    _, faces, _ = projector.project(points)
    inside = np.zeros(len(points), dtype=bool)
    for k, (point, face) in enumerate(zip(points, faces)):
        near = np.linalg.norm(sensing_map.cell_points - point, axis=1) <= reach
        if np.count_nonzero(near) < 3:
            continue
        planar = (sensing_map.cell_points[near] - point) @ projector.face_frames[face][:2].T
        try:
            inside[k] = Delaunay(planar).find_simplex(np.zeros(2)) >= 0
        except QhullError:  # all collinear (or coincident): nothing is enclosed
            continue
    return inside


def crossing_locations(sensing_map: SensingMap, count: int, rule: str, seed: int,
                       board_params: BoardParams = BoardParams()) -> tuple[np.ndarray, dict[str, Any]]:
    """``count`` touch locations (mm) near crossings by ``rule`` and how they were chosen.

    Candidates: ``20 x locations`` random points of the sensed region (within 0.8 pitch of a
    crossing, around crossings with at least the median number of neighbours;
    :meth:`ScriptBuilder.location`). Rule ``"surrounded"`` (default) keeps the candidates inside the
    tangent-plane convex hull of the crossings within two coupling widths ``2 s`` (``s`` the board's
    finger coupling width): there a nominal finger reaches crossings on at least three sides with
    >= exp(-2) = 13.5 % of its peak signal, so both tangent directions are measured, which is what
    "a location on the instrumented surface" means on hardware (the paper touched 15 such
    locations). Rule ``"near"`` keeps every candidate, including spots in gaps of a sparse layout
    where only one or two crossings see the finger (one direction then rests on the fit's priors).
    Either way the fraction of candidates the rule keeps is reported (``surrounded_fraction``), so a
    layout that leaves much of its sensed region unsurrounded shows it; farthest-point sampling
    spreads the locations over the kept candidates.
    """
    builder = ScriptBuilder(sensing_map, board_params, seed)
    candidates = np.array([builder.location("random") for _ in range(20 * count)])
    pitch = sensing_map.pitch_mm()
    width = board_params.coupling_sigma_mm or default_coupling_width_mm(board_params.finger_radius_mm, pitch)
    inside = surrounded(sensing_map, candidates, 2.0 * width)
    pool = candidates[inside] if rule == "surrounded" else candidates
    if len(pool) < count:
        raise UserError(f"only {len(pool)} of {len(candidates)} candidate locations are surrounded by crossings: "
                        "evaluate fewer locations or use location_rule 'near'")
    points = pool[farthest_point_sampling(pool, count, seed)]
    return points, {"location_rule": rule, "candidates": len(candidates),
                    "surrounded_fraction": round(float(inside.mean()), 4),
                    "locations_surrounded": int(surrounded(sensing_map, points, 2.0 * width).sum())}


