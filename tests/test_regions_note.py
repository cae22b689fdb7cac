"""The resting pose and the ingest repairs reach the run summary (table and ``--json``) and
``manifest.json`` as node notes, on the first run and on a cached one."""
from __future__ import annotations

import json

from retrotouch.graph.node import REGISTRY
from retrotouch.nodes.data.types import Mesh
from retrotouch.nodes.mesh import topology  # noqa: F401  (registers mesh.check_topology)


def test_ingest_note_lists_every_repair() -> None:
    mesh = Mesh(vertices=None, faces=None, source="m", repairs=("dropped 2 fragments", "closed 1 hole(s)"))
    note = REGISTRY["mesh.check_topology"].note_of({"mesh": mesh, "report": {}})
    assert note == "ingest repairs: dropped 2 fragments; closed 1 hole(s)"
    assert REGISTRY["mesh.check_topology"].note_of({"mesh": Mesh(None, None, "m"), "report": {}}) == "ingest repairs: none"


PREFIX = "regions[tx_pole=far]: "
"""The default pipeline maps regions.detect over its Tx poles (one, far): the note's line is the branch's."""


def test_pose_line_in_run_summary_when_ran_and_when_cached(tmp_path, cli, repo) -> None:
    command = ("run", str(repo / "pipelines" / "retrofit.yaml"), "--out", "out", "--cache-dir", "cache",
               "--target", "regions", "-S", "vertices=2000")
    for expected in ("ran", "cached"):
        table = cli(*command)
        assert table.returncode == 0, table.stderr
        pose = [line for line in table.stdout.splitlines() if line.startswith(f"{PREFIX}resting pose ")]
        assert len(pose) == 1 and "tips over at" in pose[0], table.stdout
        assert "checked: ingest repairs: " in table.stdout
        nodes = {n["node"]: n for n in json.loads((tmp_path / "out" / "manifest.json").read_text())["nodes"]}
        assert nodes["regions"]["status"] == expected and nodes["regions"]["note"] == pose[0].removeprefix(PREFIX)
        assert nodes["checked"]["note"].startswith("ingest repairs: ")
    summary = json.loads(cli(*command, "--json").stdout)
    noted = {n["node"]: n["note"] for n in summary["nodes"]}
    assert noted["regions"] == pose[0].removeprefix(PREFIX) and noted["load"] is None
