"""A pipeline's ``fallback:``: a second, wider run when the first result falls short, reusing what the
first part computed; every problem in it found before anything runs, in one line."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from retrotouch.graph.errors import UserError
from retrotouch.graph.runner import run_pipeline

from test_engine_run import SWEEP, SWEEP_TOTAL as TOTAL_3

FALLBACK = """\
fallback:
  when: {value: tot, %s}
  set: {scales: [1, 2, 3, 4]}
"""
TOTAL_4 = TOTAL_3 + 3 * 4 + 3 * 10  # one more scale, 4: (0 + 1 + 2) * 4 + 3 * 10


def run(tmp_path: Path, condition: str, overrides=(), **kw):
    path = tmp_path / "sweep.yaml"
    path.write_text(SWEEP + FALLBACK % condition)
    return run_pipeline(str(path), list(overrides), out_dir=str(tmp_path / "out"), cache_dir=str(tmp_path / "cache"),
                        scheduler="sync", **kw)


def written(tmp_path: Path) -> float:
    return json.loads((tmp_path / "out" / "value.json").read_text())


def test_a_value_that_falls_short_runs_the_wider_pipeline_computing_only_what_is_new(tmp_path, test_nodes):
    result = run(tmp_path, f"above: {TOTAL_3 - 1}")
    assert written(tmp_path) == TOTAL_4
    assert result.fallback == {"value": "tot", "read": TOTAL_3, "above": TOTAL_3 - 1, "set": ["scales=[1, 2, 3, 4]"],
                               "ran_again": True,
                               "summary": f"tot is {TOTAL_3}, above {TOTAL_3 - 1}: ran again with scales=[1, 2, 3, 4]"}
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert manifest["overrides"] == ["scales=[1, 2, 3, 4]"] and manifest["fallback"] == result.fallback
    # the first part's three branches ran; the wider run added one branch, then the new sum and the sinks
    sources = [e for e in (tmp_path / "cache" / "objects").rglob("meta.json")
               if json.loads(e.read_text())["node"].startswith("src[")]
    assert len(sources) == 4
    assert len(result.ran()) == 4 * 4 + 2  # src, plus, stats, means per scale; tot and out
    again = run(tmp_path, f"above: {TOTAL_3 - 1}")
    assert again.ran() == [] and again.fallback == result.fallback and written(tmp_path) == TOTAL_4


def test_a_value_within_bounds_runs_the_pipeline_as_it_is(tmp_path, test_nodes):
    result = run(tmp_path, f"below: {TOTAL_3 - 1}")
    assert written(tmp_path) == TOTAL_3
    assert not result.fallback["ran_again"]
    assert result.fallback["summary"] == f"tot is {TOTAL_3}, not below {TOTAL_3 - 1}: no second run"
    assert json.loads((tmp_path / "out" / "manifest.json").read_text())["overrides"] == []
    assert len(result.ran()) == 3 * 4 + 2


def test_fallback_off_by_override_and_not_for_targets(tmp_path, test_nodes):
    result = run(tmp_path, f"above: {TOTAL_3 - 1}", ["fallback=null"])
    assert written(tmp_path) == TOTAL_3 and result.fallback is None
    targeted = run(tmp_path, f"above: {TOTAL_3 - 1}", targets=["tot"])
    assert targeted.fallback is None and targeted.ran() == []


def test_a_set_already_in_effect_changes_nothing(tmp_path, test_nodes):
    result = run(tmp_path, "above: 0", ["scales=[1, 2, 3, 4]"])
    assert written(tmp_path) == TOTAL_4
    assert result.fallback["read"] is None and result.fallback["summary"].startswith("its set changes nothing")


@pytest.mark.parametrize("condition, overrides, message", [
    ("above: 1", ["fallback.when.value=tot.mean"], r"fallback value tot\.mean: tot has no 'mean'"),
    ("above: 1", ["fallback.when.value=plus"], r"node 'plus' has 3 branches; name a node with one"),
    ("above: 1", ["fallback.when.value=totl"], r"unknown node 'totl'; did you mean 'tot'\?"),
    ("above: 1, below: 2", [], r"exactly one of above and below"),
    ("abov: 1", [], r"fallback\.when: unknown key 'abov'; did you mean 'above'\?"),
    ("above: one", [], r"fallback\.when\.above must be a number"),
    ("above: 1", ["fallback.set={scalez: [1]}"], r"fallback set: -S scalez=\[1\]: unknown path 'scalez'; did you mean"),
    ("above: 1", ["fallback.set={scales: [1, 1]}"], r"fallback set: .*repeats the value 1"),
])
def test_problems_are_one_line_before_the_wider_run(tmp_path, test_nodes, condition, overrides, message):
    with pytest.raises(UserError, match=message) as caught:
        run(tmp_path, condition, overrides)
    assert "\n" not in str(caught.value)
    assert not (tmp_path / "out").exists()


def test_the_command_line_says_what_the_fallback_did_in_its_table_json_and_manifest(tmp_path, cli, test_nodes):
    import jsonschema

    schemas = Path(__file__).resolve().parents[1] / "graph" / "schemas"
    (tmp_path / "p.yaml").write_text(SWEEP + FALLBACK % f"above: {TOTAL_3 - 1}")
    plan = cli("plan", "p.yaml")
    assert plan.stdout.endswith(f"then, when tot is above {TOTAL_3 - 1}, again with scales=[1, 2, 3, 4]\n"), plan.stdout
    table = cli("run", "p.yaml", "--out", "out")
    assert table.returncode == 0, table.stderr
    assert f"fallback: tot is {TOTAL_3}, above {TOTAL_3 - 1}: ran again with scales=[1, 2, 3, 4]\n" in table.stdout
    summary = json.loads(cli("run", "p.yaml", "--out", "out", "--json").stdout)
    jsonschema.validate(summary, json.loads((schemas / "run-summary.schema.json").read_text()))
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    jsonschema.validate(manifest, json.loads((schemas / "manifest.schema.json").read_text()))
    assert summary["fallback"] == manifest["fallback"] and manifest["fallback"]["ran_again"] and summary["ran"] == 0


def test_the_two_schemas_describe_the_fallback_outcome_alike() -> None:
    """``run --json`` and ``manifest.json`` carry one outcome object; its definition is written in both
    schema files (each validates on its own, without a resolver), so they must not drift apart."""
    schemas = Path(__file__).resolve().parents[1] / "graph" / "schemas"
    summary, manifest = (json.loads((schemas / name).read_text())["properties"]["fallback"]
                         for name in ("run-summary.schema.json", "manifest.schema.json"))
    assert summary == manifest


def test_watch_says_when_the_fallback_ran_again(tmp_path, test_nodes):
    from retrotouch.graph.watch import WatchState, run_once

    (tmp_path / "p.yaml").write_text(SWEEP + FALLBACK % f"above: {TOTAL_3 - 1}")
    state = WatchState(str(tmp_path / "p.yaml"), str(tmp_path / "out"))
    line = run_once(state, [], {"cache_dir": str(tmp_path / "cache"), "scheduler": "sync"})
    assert line.endswith(f"(fallback: tot is {TOTAL_3}, above {TOTAL_3 - 1}: ran again with scales=[1, 2, 3, 4]); "
                         f"outputs in {tmp_path / 'out'}"), line
    assert written(tmp_path) == TOTAL_4
