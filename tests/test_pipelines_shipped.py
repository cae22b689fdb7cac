"""Every pipeline shipped in pipelines/ validates: its nodes exist, every declared input is
connected, every param checks against its node type."""
from __future__ import annotations

import pytest

from retrotouch.graph.runner import make_plan

from conftest import REPO

SHIPPED = sorted((REPO / "pipelines").glob("*.yaml"))


def test_the_pipelines_folder_is_not_empty():
    assert len(SHIPPED) >= 2


@pytest.mark.parametrize("pipeline", SHIPPED, ids=lambda p: p.name)
def test_shipped_pipeline_plans(pipeline, tmp_path):
    plan = make_plan(str(pipeline), [], str(tmp_path / "cache"))
    assert len(plan.instances) >= 3
    assert all(upstream or all(ref.earlier for ref in instance.decl.inputs[name])  # [<]: nothing on a first branch
               for instance in plan.instances for name, upstream in instance.inputs.items())
