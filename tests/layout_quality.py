"""One layout per mesh at test size (about 4k vertices, 60 Tx and 60 Rx candidates at one Rx angle,
the 21 x 12 board), for the tests that bound layout quality. Run as a script to print the figures
over the bunny and ../shared/meshes: ``python tests/layout_quality.py [--rings TURN | --families F,F,...] [MESH ...]``
(``--rings``: the ring family with its corridor at TURN instead of the dipole loops; ``--families``:
per mesh the best branch of each family named (``FAMILY_BRANCHES``: dipole angles ``DIPOLE_ANGLES``,
ring corridors ``RING_TURNS`` with either kind of legs, helices of either winding) as the default
pipeline sweeps them, and the best of all, by ``layout.pick_best``'s rule)."""
from __future__ import annotations

import functools
import json
import sys
from pathlib import Path

import yaml

from curves_fixture import SHARED_MESHES, prepared, sample_mesh_path

from retrotouch.nodes.curves.crossings import CrossingsParams, crossings
from retrotouch.nodes.curves.helices import TraceHelicesParams, trace_helices, winding_angle_node
from retrotouch.nodes.curves.ring_levels import RingLevelsParams, ring_levels
from retrotouch.nodes.curves.rings import TraceRingsParams, trace_rings
from retrotouch.nodes.curves.tracing import TraceRxParams, TraceTxParams, trace_rx, trace_tx
from retrotouch.nodes.layout.pick import PickParams, best_branch
from retrotouch.nodes.layout.samples import SamplesParams, surface_samples
from retrotouch.nodes.layout.sweep import AngleLayout, OptimizeParams, optimize

BUNNY = str(sample_mesh_path("bunny.obj"))
HELIX_FREE_END_MM = yaml.safe_load((Path(__file__).resolve().parents[1] / "pipelines" / "retrofit.yaml").read_text())[
    "nodes"]["helix_select"]["params"]["rx_free_end_mm"]  # the default pipeline's, for the helices
SHARED = sorted(str(p) for p in SHARED_MESHES.glob("*.ply")) if SHARED_MESHES.is_dir() else []


@functools.lru_cache(maxsize=None)
def layout_metrics(path: str, rx_angle_deg: float = 0.0, ring_turn: float | None = None, ring_legs: str = "offset",
                   helix_winding: str | None = None) -> dict:
    """The metrics of one branch, unscreened (``layout.coverage`` + ``layout.finish``), on the mesh at
    ``path`` (prepared as the curve tests do): the dipole family at ``rx_angle_deg``, the ring family
    with its corridor at ``ring_turn`` and ``ring_legs`` legs, or the helices winding ``helix_winding``."""
    mesh, regions, _, tx_field, rx_field = prepared(path, 4000)
    tx = trace_tx(TraceTxParams(n_curves=60), mesh, regions, tx_field)["curves"]
    if helix_winding is not None:
        levels = ring_levels(RingLevelsParams(), mesh, regions, tx_field, tx)
        theta = winding_angle_node(None, mesh, levels, tx_field)
        rx = trace_helices(TraceHelicesParams(winding=helix_winding), mesh, regions, levels, theta, tx, tx_field)["curves"]
    elif ring_turn is None:
        rx = trace_rx(TraceRxParams(angle_deg=rx_angle_deg, n_curves=60), mesh, regions, rx_field)["curves"]
    else:
        levels = ring_levels(RingLevelsParams(), mesh, regions, tx_field, tx)
        rx = trace_rings(TraceRingsParams(corridor_turn=ring_turn, legs=ring_legs), mesh, regions, levels, tx)["curves"]
    cross = crossings(CrossingsParams(), mesh, tx, rx, tx_field, rx_field)
    samples = surface_samples(SamplesParams(count=150), mesh, regions)
    params = OptimizeParams(rx_free_end_mm=HELIX_FREE_END_MM) if helix_winding is not None else OptimizeParams()
    candidate = optimize(params, mesh, samples, tx, rx, cross["tx_rx"], cross["tx_tx"], cross["rx_rx"])
    return {"feasible": candidate.feasible, "message": candidate.message, **candidate.metrics,
            "sensing_area_mm2": samples.sensing_area_mm2}


DIPOLE_ANGLES = (-40, -20, 0, 20, 40)
RING_TURNS = (0.0, 0.25, 0.5, 0.75)


FAMILY_BRANCHES = {
    "dipole": [{"rx_angle_deg": a} for a in DIPOLE_ANGLES],
    "rings": [{"ring_turn": t} for t in RING_TURNS],
    "rings_tx": [{"ring_turn": t, "ring_legs": "tx_lines"} for t in RING_TURNS],
    "helices": [{"helix_winding": w} for w in ("left", "right")],
}


def best_of(path: str, families: tuple[str, ...]) -> dict | None:
    """The metrics of the best branch of ``families`` on the mesh at ``path`` (None when none is feasible)."""
    candidates = []
    for family in families:
        for branch in FAMILY_BRANCHES[family]:
            m = layout_metrics(path, **branch)
            candidates.append(AngleLayout(family, 0.0, m["feasible"], m["message"], None, m))
    if not any(c.feasible for c in candidates):
        return None
    pick = PickParams()
    return candidates[best_branch(candidates, pick.radius_tolerance_mm, pick.mean_tolerance)].metrics


SUMMARY = ("cells", "channel_pairs", "voronoi_cv_all_crossings", "voronoi_cv_pads", "coverage_radius_mm",
           "min_same_layer_clearance_mm", "phase1_gap", "sensing_area_mm2")

if __name__ == "__main__":
    args = sys.argv[1:]
    turn = float(args.pop(args.index("--rings") + 1)) if "--rings" in args else None
    families = tuple(args.pop(args.index("--families") + 1).split(",")) if "--families" in args else ()
    args = [a for a in args if a not in ("--rings", "--families")]
    for path in [BUNNY] + (args or SHARED):
        try:
            if families:
                best = {f: best_of(path, (f,)) for f in families} | {"all": best_of(path, families)}
                row = {f: m and {k: m.get(k) for k in SUMMARY} for f, m in best.items()}
            else:
                m = layout_metrics(path, ring_turn=turn)
                row = {k: m.get(k) for k in SUMMARY} if m["feasible"] else {"message": m["message"]}
        except Exception as exc:  # the figures of the other meshes still count
            row = {"error": f"{type(exc).__name__}: {exc}"}
        print(json.dumps({"mesh": Path(path).stem, **row}), flush=True)
