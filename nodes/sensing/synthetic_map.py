"""A synthetic sensing map on the built-in bunny (tests, and the simulator before the pipeline's
output exists)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from scipy.optimize import linear_sum_assignment

from ..data.board import NUM_RX, NUM_TX
from ..data.builtin import BUNNY_UP, builtin_mesh_path
from ..data.sensing_map import SENSING_MAP_FORMAT, sensing_map_files, write_sensing_map
from ..geometry.surface import farthest_point_sampling


def synthetic_bunny_map(
    folder: str | Path,
    cells: int = 200,
    diagonal_mm: float = 170.0,
    base_fraction: float = 0.1,
    seed: int = 0,
    num_tx: int = NUM_TX,
    num_rx: int = NUM_RX,
) -> Path:
    """Write a realistic synthetic sensing map on the bunny into ``folder``; returns its json path.

    The bunny is scaled to ``diagonal_mm`` bounding-box diagonal; ``cells`` crossings are spread by
    farthest-point sampling over the surface above the bottom ``base_fraction`` of its height, and
    assigned to distinct (tx, rx) pairs so that Tx channels run around the object at increasing
    height and Rx channels at increasing azimuth (as the pipeline's two curve families do).
    """
    mesh = trimesh.load(builtin_mesh_path("builtin:bunny"), process=False, force="mesh")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    vertices = (vertices - vertices.min(axis=0)) * (diagonal_mm / np.linalg.norm(np.ptp(vertices, axis=0)))
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    up = BUNNY_UP
    samples, sample_faces = trimesh.sample.sample_surface(mesh, 30 * cells, seed=seed)
    height = samples @ up
    low, high = (vertices @ up).min(), (vertices @ up).max()
    keep = height > low + base_fraction * (high - low)
    samples, sample_faces = samples[keep], sample_faces[keep]
    chosen = farthest_point_sampling(samples, cells, seed)
    points, cell_faces = samples[chosen], sample_faces[chosen]
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[cell_faces], points)
    rank_height = np.argsort(np.argsort(points @ up)) / max(cells - 1, 1)
    centre = points.mean(axis=0)
    side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    azimuth = np.arctan2((points - centre) @ np.cross(up, side), (points - centre) @ side)
    rank_azimuth = np.argsort(np.argsort(azimuth)) / max(cells - 1, 1)
    tx_target = (np.arange(num_tx) + 0.5) / num_tx
    rx_target = (np.arange(num_rx) + 0.5) / num_rx
    cost = ((rank_height[:, None, None] - tx_target[None, :, None]) ** 2
            + (rank_azimuth[:, None, None] - rx_target[None, None, :]) ** 2).reshape(cells, -1)
    rows, slots = linear_sum_assignment(cost)
    cell_tx, cell_rx = np.divmod(slots[np.argsort(rows)], num_rx)  # slot = tx * num_rx + rx of the cost matrix
    points = np.einsum("kj,kjd->kd", bary, vertices[faces[cell_faces]])
    channels = {layer: [(c, _channel_length(points[ids == c])) for c in range(count)]
                for layer, ids, count in (("tx", cell_tx, num_tx), ("rx", cell_rx, num_rx))}
    face_height = vertices[faces].mean(axis=1) @ up
    sensing_faces = face_height > low + base_fraction * (high - low)
    files = sensing_map_files(vertices, faces, up, cell_tx, cell_rx, points, cell_faces, bary,
                              np.ones(len(cell_tx), dtype=bool), channels, sensing_faces)
    return write_sensing_map(folder, files)


def _channel_length(points: np.ndarray) -> float:
    """Length (mm) of the polyline through a channel's crossings ordered greedily (a synthetic stand-in)."""
    if len(points) < 2:
        return 0.0
    order = [0]
    rest = list(range(1, len(points)))
    while rest:
        last = points[order[-1]]
        nearest = min(rest, key=lambda i: float(np.sum((points[i] - last) ** 2)))
        order.append(nearest)
        rest.remove(nearest)
    return round(float(np.sum(np.linalg.norm(np.diff(points[order], axis=0), axis=1))), 3)


def default_sensing_map_path(repo_root: str | Path, cache_folder: str | Path) -> tuple[Path, str]:
    """The real default pipeline output ``out/retrofit/sensing_map.json`` if present, else the
    synthetic bunny map (generated once per format version into ``cache_folder``). Returns (path,
    description)."""
    real = Path(repo_root) / "out" / "retrofit" / "sensing_map.json"
    if real.is_file():
        return real, f"default pipeline output {real}"
    cache = Path(cache_folder) / SENSING_MAP_FORMAT.replace("/", "-").replace(".", "_")
    path = cache / "sensing_map.json"
    if not path.is_file():
        path = synthetic_bunny_map(cache)
    return path, f"synthetic bunny map {path} (out/retrofit/sensing_map.json not found)"
