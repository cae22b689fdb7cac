"""``sensing_map.json``: the layout as the touch runtime reads it, with its one writer and one reader.

Written next to ``mesh.ply`` (the object's mesh, :func:`..data.ply.ply_bytes`) in a run's output::

    {"format": "retrotouch.sensing_map/2",
     "units": "mm",
     "up": [ux, uy, uz],                            # unit, opposite to the side the object rests on
     "mesh": {"file": "mesh.ply", "sha256": "<hex of the file bytes>", "vertices": n, "faces": m},
     "design": {"pad_radius_mm": 2.0, "d_min_mm": 8.0, "trace_width_mm": 1.0, "clearance_mm": 1.0},  # as laid out
     "sensing_faces": [[start, stop], ...],         # face index ranges of the sensing region a finger can touch
     "tx_channels": 21, "rx_channels": 12,          # channels wired (= selected curves per layer)
     "channels": {"tx": [{"channel": 0, "name": "Tx00", "curve": 17, "length_mm": 123.4}, ...],
                  "rx": [{"channel": 0, "name": "Rx00", "curve": 4, "length_mm": 98.7}, ...]},
     "cells": [{"tx": 0, "rx": 3, "point": [x, y, z], "face": 123, "bary": [l0, l1, l2],
                "normal": [nx, ny, nz], "pad": true}, ...]}

Cells list only channel pairs whose curves cross (at most one cell per pair); the board frame index
of a cell is ``tx * NUM_RX + rx`` (:mod:`.board`). A cell's normal is the barycentric interpolation
of the unit area-weighted vertex normals (:func:`..geometry.triangles.surface_normals`), normalised:
smooth across faces, outward because faces are CCW seen from outside. The sensing region
(``regions.detect``: where traces may run, base and exclusions left out), cut to the faces a finger
can touch (``regions.touchable``), is what an evaluation spreads its touch locations over. Version 2
added ``up`` and ``sensing_faces``; the reader refuses version 1 files (their up axis is unknown)
with a one-line error saying to re-run the pipeline.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ...graph.errors import UserError
from ..geometry.triangles import surface_normals
from .board import NUM_RX, NUM_TX
from .ply import ply_bytes

SENSING_MAP_FORMAT = "retrotouch.sensing_map/2"
SENSING_MAP_FILE = "sensing_map.json"
MESH_FILE = "mesh.ply"


@dataclasses.dataclass(frozen=True)
class SensingMap:
    """A layout as the runtime sees it: the mesh (mm), its up axis and, per cell, its channels and
    3D crossing."""

    vertices: np.ndarray  # (n, 3) float64, mm
    faces: np.ndarray  # (m, 3) int64
    up: np.ndarray  # (3,) float64, unit
    sensing_faces: np.ndarray  # (m,) bool, the sensing region a finger can touch
    num_tx: int  # Tx channels wired (<= NUM_TX)
    num_rx: int  # Rx channels wired (<= NUM_RX)
    cell_tx: np.ndarray  # (K,) int64
    cell_rx: np.ndarray  # (K,) int64
    cell_points: np.ndarray  # (K, 3) float64, mm
    cell_faces: np.ndarray  # (K,) int64
    cell_bary: np.ndarray  # (K, 3) float64
    cell_normals: np.ndarray  # (K, 3) float64, unit
    cell_pad: np.ndarray  # (K,) bool
    source: str  # the sensing_map.json it came from

    @property
    def cell_count(self) -> int:
        return len(self.cell_tx)

    @property
    def frame_index(self) -> np.ndarray:
        """Index of each cell in a flattened channel-order board frame (``tx * NUM_RX + rx``,
        whatever number of channels the layout wires)."""
        return self.cell_tx * NUM_RX + self.cell_rx

    def pitch_mm(self) -> float:
        """Median distance from a cell to its nearest neighbour cell (mm)."""
        distances, _ = cKDTree(self.cell_points).query(self.cell_points, k=2)
        return float(np.median(distances[:, 1]))


def sensing_map_files(
    vertices: np.ndarray,
    faces: np.ndarray,
    up: np.ndarray,
    cell_tx: np.ndarray,
    cell_rx: np.ndarray,
    cell_points: np.ndarray,
    cell_faces: np.ndarray,
    cell_bary: np.ndarray,
    cell_pad: np.ndarray,
    channels: dict[str, list[tuple[int, float]]],
    sensing_faces: np.ndarray,
    design: dict[str, float] | None = None,
) -> dict[str, bytes]:
    """The bytes of ``sensing_map.json`` and ``mesh.ply`` for a layout: mesh (mm), ``up`` (3,), the
    sensing region ``sensing_faces`` (m,) bool, per cell its channels, crossing point (mm), face,
    barycentrics and pad flag, per layer (``"tx"``, ``"rx"``) one ``(curve id, length_mm)`` per
    channel in channel order, and the design values the layout was made with (mm; written when
    given)."""
    mesh_bytes = ply_bytes(vertices, faces)
    up = np.asarray(up, dtype=np.float64)
    normals = surface_normals(vertices, faces, cell_faces, cell_bary)

    def layer(name: str, prefix: str) -> list[dict]:
        return [{"channel": i, "name": f"{prefix}{i:02d}", "curve": int(curve), "length_mm": float(length)}
                for i, (curve, length) in enumerate(channels[name])]

    document = {
        "format": SENSING_MAP_FORMAT,
        "units": "mm",
        "up": [float(v) for v in up / np.linalg.norm(up)],
        "mesh": {"file": MESH_FILE, "sha256": hashlib.sha256(mesh_bytes).hexdigest(),
                 "vertices": int(len(vertices)), "faces": int(len(faces))},
        **({"design": {name: float(value) for name, value in design.items()}} if design is not None else {}),
        "sensing_faces": face_ranges(sensing_faces),
        "tx_channels": len(channels["tx"]),
        "rx_channels": len(channels["rx"]),
        "channels": {"tx": layer("tx", "Tx"), "rx": layer("rx", "Rx")},
        "cells": [{"tx": int(cell_tx[k]), "rx": int(cell_rx[k]), "point": [float(v) for v in cell_points[k]],
                   "face": int(cell_faces[k]), "bary": [float(v) for v in cell_bary[k]],
                   "normal": [float(v) for v in normals[k]], "pad": bool(cell_pad[k])}
                  for k in range(len(cell_tx))],
    }
    return {SENSING_MAP_FILE: json.dumps(document, indent=1).encode(), MESH_FILE: mesh_bytes}


def face_ranges(mask: np.ndarray) -> list[list[int]]:
    """``[[start, stop], ...]`` half-open index ranges of the True runs of a (m,) bool mask."""
    padded = np.concatenate([[False], np.asarray(mask, dtype=bool), [False]])
    edges = np.flatnonzero(padded[1:] != padded[:-1])
    return [[int(a), int(b)] for a, b in zip(edges[::2], edges[1::2])]


def face_mask(ranges: list[list[int]], count: int) -> np.ndarray:
    """The (count,) bool mask of :func:`face_ranges` output (ValueError outside 0..count)."""
    mask = np.zeros(count, dtype=bool)
    for start, stop in ranges:
        if not 0 <= int(start) < int(stop) <= count:
            raise ValueError(f"face range [{start}, {stop}) outside 0..{count}")
        mask[int(start):int(stop)] = True
    return mask


def write_sensing_map(folder: str | Path, files: dict[str, bytes]) -> Path:
    """Write :func:`sensing_map_files` output into ``folder`` (created); returns the json path."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for name, data in files.items():
        (folder / name).write_bytes(data)
    return folder / SENSING_MAP_FILE


def resolve_sensing_map_path(path: str | Path) -> Path:
    """A sensing_map.json or a run folder holding one -> the json path (UserError if neither)."""
    path = Path(path)
    if path.is_dir():
        path = path / SENSING_MAP_FILE
    if not path.is_file():
        raise UserError(f"sensing map {path} not found: pass --layout <run folder or sensing_map.json>")
    return path


def _read_document(path: Path) -> dict:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise UserError(f"sensing map {path} is not valid JSON ({exc}): regenerate it with the pipeline") from None
    if not isinstance(doc, dict) or doc.get("format") != SENSING_MAP_FORMAT:
        found = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise UserError(f"sensing map {path} has format {found!r}, expected {SENSING_MAP_FORMAT!r}: "
                        "re-run the pipeline to regenerate it")
    return doc


def load_sensing_map(path: str | Path) -> SensingMap:
    """Read ``sensing_map.json`` (:data:`SENSING_MAP_FORMAT`) and its mesh; one-line UserError on a
    missing file, a bad schema or a mesh that does not match the recorded sha256."""
    import trimesh  # heavy: imported when reading, not on node discovery

    path = resolve_sensing_map_path(path)
    doc = _read_document(path)
    try:
        mesh_file = path.parent / doc["mesh"]["file"]
        num_tx, num_rx = int(doc["tx_channels"]), int(doc["rx_channels"])
        up = np.array(doc["up"], dtype=np.float64).reshape(3)
        sensing_ranges = doc["sensing_faces"]
        cells = doc["cells"]
        cell_tx = np.array([c["tx"] for c in cells], dtype=np.int64)
        cell_rx = np.array([c["rx"] for c in cells], dtype=np.int64)
        points = np.array([c["point"] for c in cells], dtype=np.float64).reshape(-1, 3)
        faces_k = np.array([c["face"] for c in cells], dtype=np.int64)
        bary = np.array([c["bary"] for c in cells], dtype=np.float64).reshape(-1, 3)
        normals = np.array([c["normal"] for c in cells], dtype=np.float64).reshape(-1, 3)
        pad = np.array([bool(c["pad"]) for c in cells], dtype=bool)
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"sensing map {path} misses or mangles field {exc}: regenerate it with the pipeline") from None
    _check_cells(path, num_tx, num_rx, cell_tx, cell_rx, up)
    if not mesh_file.is_file():
        raise UserError(f"mesh {mesh_file} named by {path} not found: keep mesh.ply next to sensing_map.json")
    expected = doc["mesh"].get("sha256")
    if expected and hashlib.sha256(mesh_file.read_bytes()).hexdigest() != expected:
        raise UserError(f"mesh {mesh_file} does not match the sha256 in {path}: re-run the pipeline")
    mesh = trimesh.load(mesh_file, process=False, force="mesh")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if faces_k.max() >= len(faces):
        raise UserError(f"sensing map {path} names face {faces_k.max()} but {mesh_file} has {len(faces)} faces")
    try:
        sensing = face_mask(sensing_ranges, len(faces))
    except (TypeError, ValueError) as exc:
        raise UserError(f"sensing map {path} has bad sensing_faces ({exc}): regenerate it with the pipeline") from None
    return SensingMap(vertices, faces, up / np.linalg.norm(up), sensing, num_tx, num_rx, cell_tx, cell_rx, points, faces_k,
                      bary, normals / np.linalg.norm(normals, axis=1, keepdims=True), pad, str(path))


def _check_cells(path: Path, num_tx: int, num_rx: int, cell_tx: np.ndarray, cell_rx: np.ndarray,
                 up: np.ndarray) -> None:
    if len(cell_tx) == 0:
        raise UserError(f"sensing map {path} lists no cells: the layout has no Tx/Rx crossings")
    if num_tx > NUM_TX or num_rx > NUM_RX:
        raise UserError(f"sensing map {path} wires {num_tx} x {num_rx} channels but the Muca board has {NUM_TX} x {NUM_RX}")
    if cell_tx.min() < 0 or cell_tx.max() >= num_tx or cell_rx.min() < 0 or cell_rx.max() >= num_rx:
        raise UserError(f"sensing map {path} has cell channels outside {num_tx} x {num_rx}")
    if len(np.unique(cell_tx * num_rx + cell_rx)) != len(cell_tx):
        raise UserError(f"sensing map {path} lists a (tx, rx) pair twice")
    if not np.all(np.isfinite(up)) or np.linalg.norm(up) < 0.5:
        raise UserError(f"sensing map {path} has up axis {up.tolist()}, not a unit vector: re-run the pipeline")
