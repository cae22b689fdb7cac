"""layout.coverage + layout.finish -> layout.pick_best -> layout.sensing_map on the synthetic sphere instance."""
from __future__ import annotations

import dataclasses
import hashlib
import io
import json

import numpy as np
import pytest
import trimesh
from test_layout_fixtures import synthetic_instance

from retrotouch.graph.errors import UserError
from retrotouch.nodes.data.sensing_map import SENSING_MAP_FORMAT
from retrotouch.nodes.layout.pick import PickParams, pick_best
from retrotouch.nodes.layout.sweep import OptimizeParams, optimize
from retrotouch.nodes.layout.sensing_map import SensingMapParams, write_sensing_map
from retrotouch.nodes.layout.samples import SamplesParams, surface_samples


@pytest.fixture(scope="module")
def run():
    mesh, regions, tx, rx, tx_rx, tx_tx, rx_rx = synthetic_instance()
    samples = surface_samples(SamplesParams(count=150), mesh, regions)
    params = OptimizeParams(n_drive=8, n_sense=5, time_limit_s=2.0)
    a = optimize(params, mesh, samples, tx, rx, tx_rx, tx_tx, rx_rx)
    rx_other = dataclasses.replace(rx, angle=np.deg2rad(-10.0))
    b = optimize(params.model_copy(update={"n_sense": 3}), mesh, samples, tx, rx_other, tx_rx, tx_tx, rx_rx)
    picked = pick_best(PickParams(print_table=False), [a, b])
    files = write_sensing_map(SensingMapParams(), mesh, regions, picked["layout"], picked["metrics"])
    return mesh, (a, b), picked, files


def validate_sensing_map(doc: dict, n_tx_max: int = 21, n_rx_max: int = 12) -> None:
    """Structure and types exactly as the format in retrotouch.nodes.data.sensing_map."""
    assert set(doc) == {"format", "units", "up", "mesh", "design", "sensing_faces", "tx_channels", "rx_channels",
                        "channels", "cells"}
    assert all(0 <= a < b <= doc["mesh"]["faces"] for a, b in doc["sensing_faces"])
    assert doc["format"] == SENSING_MAP_FORMAT and doc["units"] == "mm"
    assert len(doc["up"]) == 3 and np.linalg.norm(doc["up"]) == pytest.approx(1.0)
    assert set(doc["mesh"]) == {"file", "sha256", "vertices", "faces"}
    assert doc["mesh"]["file"] == "mesh.ply" and len(doc["mesh"]["sha256"]) == 64
    for layer, prefix, limit in (("tx", "Tx", n_tx_max), ("rx", "Rx", n_rx_max)):
        channels = doc["channels"][layer]
        assert len(channels) == doc[f"{layer}_channels"] <= limit
        for i, ch in enumerate(channels):
            assert set(ch) == {"channel", "name", "curve", "length_mm"}
            assert ch["channel"] == i and ch["name"] == f"{prefix}{i:02d}"
            assert isinstance(ch["curve"], int) and ch["length_mm"] > 0
    pairs = set()
    for cell in doc["cells"]:
        assert set(cell) == {"tx", "rx", "point", "face", "bary", "normal", "pad"}
        assert 0 <= cell["tx"] < doc["tx_channels"] and 0 <= cell["rx"] < doc["rx_channels"]
        assert len(cell["point"]) == 3 and len(cell["bary"]) == 3 and len(cell["normal"]) == 3
        assert sum(cell["bary"]) == pytest.approx(1.0) and min(cell["bary"]) >= 0
        assert np.linalg.norm(cell["normal"]) == pytest.approx(1.0)
        assert isinstance(cell["pad"], bool) and isinstance(cell["face"], int)
        pairs.add((cell["tx"], cell["rx"]))
    assert len(pairs) == len(doc["cells"])  # at most one cell per channel pair


def test_sensing_map_matches_schema_and_mesh(run):
    mesh, _, picked, files = run
    assert set(files.contents) == {"sensing_map.json", "mesh.ply", "metrics.json"}
    doc = json.loads(files.contents["sensing_map.json"])
    validate_sensing_map(doc)
    ply = files.contents["mesh.ply"]
    assert doc["mesh"]["sha256"] == hashlib.sha256(ply).hexdigest()
    assert ply.startswith(b"ply\nformat binary_little_endian")
    loaded = trimesh.load(io.BytesIO(ply), file_type="ply", process=False)
    assert np.allclose(loaded.vertices, mesh.vertices) and np.array_equal(loaded.faces, mesh.faces)
    assert (doc["mesh"]["vertices"], doc["mesh"]["faces"]) == (len(mesh.vertices), len(mesh.faces))
    layout = picked["layout"]
    for cell, point, face in zip(doc["cells"], layout.cells.points, layout.cells.faces):
        assert np.allclose(cell["point"], point) and cell["face"] == face
        corners = mesh.vertices[mesh.faces[cell["face"]]]
        assert np.allclose(np.asarray(cell["bary"]) @ corners, cell["point"], atol=1e-6)
        assert np.dot(cell["normal"], cell["point"]) > 0  # outward on the sphere
    assert sum(c["pad"] for c in doc["cells"]) == picked["metrics"]["pads"] == int(layout.pad.sum())
    assert doc["up"] == [0.0, 0.0, 1.0]  # the regions' resting pose
    regions = synthetic_instance()[1]
    assert sum(b - a for a, b in doc["sensing_faces"]) == int(regions.sensing_faces.sum())


def test_metrics_json_follows_its_json_schema(run):
    """nodes/data/metrics.schema.json: the written file validates (no key outside the schema), its
    format constant is the writer's, and a file without the pose does not."""
    jsonschema = pytest.importorskip("jsonschema")
    from pathlib import Path

    from retrotouch.nodes.data import metrics_file

    schema = json.loads((Path(metrics_file.__file__).parent / "metrics.schema.json").read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    assert schema["properties"]["format"]["const"] == metrics_file.METRICS_FORMAT
    doc = json.loads(run[3].contents["metrics.json"])
    jsonschema.validate(doc, schema)
    assert doc["pose"]["up"] == [0.0, 0.0, 1.0]
    del doc["pose"]
    with pytest.raises(jsonschema.ValidationError, match="'pose' is a required property"):
        jsonschema.validate(doc, schema)


def test_metrics_and_pick(run):
    _, (a, b), picked, files = run
    metrics = json.loads(files.contents["metrics.json"])
    for key in ("voronoi_cv", "coverage_radius_mm", "mean_distance_mm", "pads", "min_pad_spacing_mm",
                "curve_lengths_mm", "phase1", "phase2", "relaxations", "angles", "chosen_angle_deg"):
        assert key in metrics
    assert [row["angle_deg"] for row in metrics["angles"]] == pytest.approx([10.0, -10.0])
    assert metrics["min_pad_spacing_mm"] >= metrics["d_min_mm"]
    assert b.metrics["rx_channels"] <= 3  # pin-count override reaches the branch
    radius = min(c.metrics["coverage_radius_mm"] for c in (a, b))
    tied = [c for c in (a, b) if c.metrics["coverage_radius_mm"] <= radius + 1.0]
    best = min(tied, key=lambda c: c.metrics["power_mean_distance_mm"])
    assert metrics["chosen_angle_deg"] == pytest.approx(best.angle_deg)
    layout = picked["layout"]
    assert layout.tx.count == len(layout.tx_source) == metrics["tx_channels"]
    assert np.allclose(layout.tx.lengths_mm, metrics["curve_lengths_mm"]["tx"])


def test_all_infeasible_branches_give_a_user_error(run):
    _, (a, _), _, _ = run
    bad = dataclasses.replace(a, feasible=False, layout=None, message="no pad placement")
    with pytest.raises(UserError, match="no branch gives a feasible layout"):
        pick_best(PickParams(print_table=False), [bad])
