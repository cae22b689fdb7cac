"""End to end, one test per class of object (tests/shapes.py), with no overrides of the pose or base:
the default pipeline's ingest, regions, curves and layout nodes (pipelines/retrofit.yaml without
the fabrication, preview and projection sinks), at a small vertex count and one Rx angle, run as
the ``retrotouch run`` command."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import jsonschema
import numpy as np
import pytest
import trimesh
import yaml

import shapes
from touch_fixture import touch_of
from retrotouch.nodes.data.types import Mesh
from retrotouch.nodes.regions.detect import RegionParams, detect_regions

REPO = Path(__file__).resolve().parents[1]
METRICS_SCHEMA = json.loads((REPO / "nodes" / "data" / "metrics.schema.json").read_text())
KEEP_UP_TO = "sensing_map"
"""The last node kept from the default pipeline (what follows it are sinks that need no class test)."""
VERTICES = 1500

EXPECTED_POSE = {
    "plate": "thin",
    "bowl_foot_ring": "foot_ring",
    "four_legged_figurine": "patches",
    "standing_figure": "patches",
    "figure_arms_out": "patches",
    "lying_spoon": "round",
    "metal_spoon": "thin",
    "bust_cut_base": "flat",
    "box": "flat",
    "phone": "thin",
    "starfish": "thin",
    "vase": "flat",
    "point_cloud_scan": "flat",
}


def trimmed_pipeline(folder: Path) -> Path:
    """The default pipeline cut after ``KEEP_UP_TO``, without its fallback (the second sweep with the
    centre pole too; test_engine_fallback and the pole sweep below test it), written into ``folder``."""
    document = yaml.safe_load((REPO / "pipelines" / "retrofit.yaml").read_text())
    document.pop("fallback")
    names = list(document["nodes"])
    document["nodes"] = {name: document["nodes"][name] for name in names[: names.index(KEEP_UP_TO) + 1]}
    path = folder / "classes.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def run_class(tmp_path: Path, name: str, *overrides: str) -> Path:
    """The trimmed pipeline on the generated ``name`` at ``VERTICES``, one Rx angle, one helix winding and climb, one
    grid and no rings (as the first sweep; one ring climb where ``overrides`` add a corridor), plus ``-S``
    ``overrides``, as the ``retrotouch run`` command; its output folder."""
    mesh_path = shapes.write_shape(name, tmp_path)
    out = tmp_path / "out"
    command = [
        sys.executable, "-m", "retrotouch.nodes", "run", str(trimmed_pipeline(tmp_path)),
        "--out", str(out), "--cache-dir", str(tmp_path / "cache"), "--scheduler", "sync",
        "-S", f"mesh={mesh_path}", "-S", f"diagonal_mm={shapes.diagonal_mm(name)}",
        "-S", f"vertices={VERTICES}", "-S", "rx_angles_deg=[0]", "-S", "ring_climbs=[median]",
        "-S", "helix_windings=[left]", "-S", "helix_climbs=[median]", "-S", "grid_tx=[across]",
    ]
    for override in overrides:
        command += ["-S", override]
    done = subprocess.run(command, capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    return out


@pytest.mark.parametrize("name", sorted(EXPECTED_POSE))
def test_class_runs_end_to_end_without_overrides(tmp_path: Path, name: str) -> None:
    out = run_class(tmp_path, name)
    metrics = json.loads((out / "metrics.json").read_text())
    jsonschema.validate(metrics, METRICS_SCHEMA)
    assert metrics["feasible"]
    assert metrics["voronoi_cv"] < 1.5
    # cells over the sensing region: no point of it farther than 0.5 x the object's diagonal from a
    # cell (a sanity bound, not the quality goal: with the same-layer clearance constraint the
    # figurine's legs measure 0.43 at this resolution, 0.35 without it)
    assert metrics["coverage_radius_mm"] < 0.5 * shapes.diagonal_mm(name)
    checked = trimesh.load(str(out / "mesh.ply"), process=False)
    mesh = Mesh(np.asarray(checked.vertices, dtype=np.float64), np.asarray(checked.faces, dtype=np.int64), name)
    regions = detect_regions(RegionParams(), mesh, touch_of(mesh))
    assert regions.pose_kind == EXPECTED_POSE[name], regions.pose_reason
    assert regions.tipping_angle_deg >= RegionParams().min_tipping_deg
    if name == "vase":  # the inside below a finger's reach, about a third of the surface, joins the far exclusion
        assert metrics["pose"]["sensing_area_fraction"] < 0.7 and metrics["touch"]["share"] < 0.7
    if name == "point_cloud_scan":
        assert abs(np.ptp(mesh.vertices, axis=0)[2] - 160.0) < 10.0  # fragments dropped: only the bust's height
    if name == "four_legged_figurine":  # standing on one leg's foot, the other three legs are limbs (about 35 mm deep)
        legs = [limb for limb in metrics["limbs"] if limb["depth_mm"] > 25.0]
        assert len(legs) >= 3 and all(0 < limb["area_mm2"] and limb["cells"] <= metrics["cells"] for limb in legs)
    if name == "figure_arms_out":  # the far pole tips a stretched hand, the top pole the head
        height = mesh.vertices @ regions.up
        top = detect_regions(RegionParams(tx_pole="top"), mesh, touch_of(mesh))
        share = lambda v: (height[v] - height.min()) / np.ptp(height)  # noqa: E731
        assert share(regions.far_vertex) < 0.85 and share(top.far_vertex) > 0.95
    if name == "phone":  # a wide flat top: a grid's lines spread over it like a touch panel's (the plan's 7.0 mm, the
        # geodesic one's 6.5 mm, the helices 24 mm)
        assert metrics["rx_family"] in ("grid", "grid_plan") and metrics["coverage_radius_mm"] < 10.0, metrics["coverage_radius_mm"]
    assert metrics["pads"] >= 10 and metrics["cells"] >= 20, (metrics["pads"], metrics["cells"])


def test_the_pole_sweep_picks_over_both_tx_poles_and_hands_on_the_chosen_regions(tmp_path: Path) -> None:
    """``-S tx_poles=[far, centre]`` with one ring corridor, as the fallback sweeps: every branch runs around each
    Tx pole, screened and picked as one sweep; the sensing map's pose names the chosen branch's pole and its
    sensing share is that pole's. (Rings with side-by-side legs, helices and both grids: the other families
    map the same way.)"""
    out = run_class(tmp_path, "four_legged_figurine", "tx_poles=[far, centre]", "rx_angles_deg=[]", "corridor_turns=[0.0]",
                    "ring_legs=[offset]")
    metrics = json.loads((out / "metrics.json").read_text())
    jsonschema.validate(metrics, METRICS_SCHEMA)
    rows = metrics["angles"]
    assert sorted(r["tx_pole"] for r in rows) == ["centre"] * 4 + ["far"] * 4  # rings, helices, both grids per pole
    finished = [r for r in rows if r["coverage_radius_mm"] is not None]
    chosen = min(finished, key=lambda r: r["coverage_radius_mm"])
    assert metrics["coverage_radius_mm"] <= chosen["coverage_radius_mm"] + 1.0  # pick_best's radius tolerance
    assert metrics["pose"]["tx_pole"] in {r["tx_pole"] for r in finished}
    checked = trimesh.load(str(out / "mesh.ply"), process=False)
    mesh = Mesh(np.asarray(checked.vertices, dtype=np.float64), np.asarray(checked.faces, dtype=np.int64), "figurine")
    regions = detect_regions(RegionParams(tx_pole=metrics["pose"]["tx_pole"]), mesh, touch_of(mesh))
    assert abs(regions.sensing_area_fraction - metrics["pose"]["sensing_area_fraction"]) < 1e-9
    ranges = json.loads((out / "sensing_map.json").read_text())["sensing_faces"]  # half-open, the touchable ones
    written = np.zeros(len(mesh.faces), dtype=bool)
    for start, stop in ranges:
        written[start:stop] = True
    assert not (written & ~regions.sensing_faces).any()
    # the run read the touch field of the mesh before remeshing, this check that of the remeshed one
    assert np.count_nonzero(written != regions.touch_faces) <= 0.01 * regions.sensing_faces.sum()
