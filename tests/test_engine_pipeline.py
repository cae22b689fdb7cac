"""YAML pipelines: every mistake is one line with file:line:col, and -S overrides."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from retrotouch.graph.dag import to_mermaid
from retrotouch.graph.errors import UserError
from retrotouch.graph.runner import make_plan, run_pipeline

GOOD = """\
params:
  n: 3
  deltas: [1, 2]
nodes:
  src:
    type: t.source
    params:
      n: "${n}"
  plus:
    type: t.add
    inputs: {x: src}
    map: {delta: "${deltas}"}
  tot:
    type: t.sum
    inputs: {xs: "plus[*]"}
"""


def error_of(tmp_path: Path, text: str, overrides=()) -> str:
    path = tmp_path / "p.yaml"
    path.write_text(text)
    with pytest.raises(UserError) as info:
        make_plan(str(path), list(overrides), str(tmp_path / "cache"))
    message = str(info.value)
    assert "\n" not in message
    return message.replace(str(path), "p.yaml")


def test_good_pipeline_expands_branches_and_fan_in(tmp_path, test_nodes):
    path = tmp_path / "p.yaml"
    path.write_text(GOOD)
    plan = make_plan(str(path), [], str(tmp_path))
    assert [i.id for i in plan.instances] == ["src", "plus[delta=1]", "plus[delta=2]", "tot"]
    tot = plan.instances[-1]
    assert [u.id for u, _ in tot.inputs["xs"]] == ["plus[delta=1]", "plus[delta=2]"]
    assert plan.instances[0].params.n == 3  # "${n}" kept its int type


def test_misspelt_param_points_at_its_line_with_a_suggestion(tmp_path, test_nodes):
    msg = error_of(tmp_path, GOOD.replace('      n: "${n}"', '      nn: "${n}"'))
    assert msg == "p.yaml:8:7: node 'src' (t.source): unknown param 'nn'; did you mean 'n'?"


def test_wrong_type_points_at_the_value(tmp_path, test_nodes):
    msg = error_of(tmp_path, GOOD.replace("  n: 3", "  n: three"))
    assert msg.startswith("p.yaml:8:10: node 'src' (t.source): param 'n': Input should be a valid integer")


def test_unknown_node_type_suggests_the_closest(tmp_path, test_nodes):
    msg = error_of(tmp_path, GOOD.replace("type: t.add", "type: t.ad"))
    assert msg == "p.yaml:10:11: node 'plus': unknown node type 't.ad'; did you mean 't.add'?"


def test_missing_input(tmp_path, test_nodes):
    msg = error_of(tmp_path, GOOD.replace("    inputs: {x: src}\n", ""))
    assert msg == "p.yaml:9:3: node 'plus' (t.add): input 'x' is not connected; add inputs: {x: <node>}"


def test_unknown_input_and_unknown_upstream(tmp_path, test_nodes):
    assert error_of(tmp_path, GOOD.replace("{x: src}", "{x: src, z: src}")).startswith(
        "p.yaml:11:22: node 'plus' (t.add): unknown input 'z' (inputs: x)")
    assert error_of(tmp_path, GOOD.replace("{x: src}", "{x: scr}")) == \
        "p.yaml:11:17: node 'plus': input 'x' refers to unknown node 'scr'; did you mean 'src'?"


def test_cycle(tmp_path, test_nodes):
    text = "nodes:\n  a: {type: t.add, inputs: {x: b}}\n  b: {type: t.add, inputs: {x: a}}\n"
    assert error_of(tmp_path, text) == "p.yaml:3:32: cycle: a -> b -> a"


def test_bad_map_values(tmp_path, test_nodes):
    assert error_of(tmp_path, GOOD.replace("deltas: [1, 2]", "deltas: 5")) == \
        "p.yaml:12:18: node 'plus': map 'delta' needs a list of values ([] for no branch), got 5"
    assert error_of(tmp_path, GOOD.replace("deltas: [1, 2]", "deltas: [1, oops]")).startswith(
        "p.yaml:12:18: node 'plus' (t.add): param 'delta': Input should be a valid number")
    assert error_of(tmp_path, GOOD.replace("map: {delta:", "map: {delt:")).startswith(
        "p.yaml:12:11: node 'plus' (t.add): cannot map over unknown param 'delt'; did you mean 'delta'?")


def test_repeated_map_values_are_refused_before_anything_runs(tmp_path, test_nodes):
    assert error_of(tmp_path, GOOD.replace("deltas: [1, 2]", "deltas: [1, 2, 1]")) == \
        "p.yaml:12:18: node 'plus': map 'delta' repeats the value 1; list each value once"
    literal = GOOD.replace('map: {delta: "${deltas}"}', "map: {delta: [3, 4, 4]}")
    assert error_of(tmp_path, literal) == "p.yaml:12:25: node 'plus': map 'delta' repeats the value 4; list each value once"
    assert error_of(tmp_path, GOOD, ["deltas=[6, 6]"]) == \
        "-S deltas=[6, 6] (used at p.yaml:12:18): node 'plus': map 'delta' repeats the value 6; list each value once"


def test_unknown_interpolation_and_keys(tmp_path, test_nodes):
    assert error_of(tmp_path, GOOD.replace('"${n}"', '"${m}"')) == \
        "p.yaml:8:10: unknown pipeline param ${m} (defined: n, deltas)"
    assert error_of(tmp_path, GOOD.replace("    type: t.source", "    typ: t.source")).startswith(
        "p.yaml:6:5: node 'src': unknown key 'typ'; did you mean 'type'?")
    assert error_of(tmp_path, GOOD + "  tot:\n    type: t.sum\n").startswith("p.yaml:16:3: duplicate key 'tot'")
    assert re.match(r"p\.yaml:\d+:\d+: YAML syntax error", error_of(tmp_path, GOOD.replace("{x: src}", "{x: src")))


def test_fan_in_of_an_unmapped_node_is_refused(tmp_path, test_nodes):
    msg = error_of(tmp_path, GOOD.replace('"plus[*]"', '"src[*]"'))
    assert msg.startswith("p.yaml:15:18: node 'tot': input 'xs' fans in src[*]")


def test_a_fan_in_list_into_an_input_that_takes_one_value_is_refused(tmp_path, test_nodes):
    """t.stats annotates ``x`` as one array, t.sum ``xs`` as a list: only the list takes plus[*]."""
    text = GOOD + '  st:\n    type: t.stats\n    inputs: {x: "plus[*]"}\n'
    assert error_of(tmp_path, text) == (
        "p.yaml:18:17: node 'st' (t.stats): input 'x' takes one value, but plus[*] hands it a list of every "
        "branch: write plus (the node then runs once per branch), or feed the list to a node that takes one")
    make_plan(str(_written(tmp_path, text.replace('"plus[*]"}\n', "plus}\n"))), [], str(tmp_path / "cache"))


def _written(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "q.yaml"
    path.write_text(text)
    return path


def test_overrides(tmp_path, test_nodes):
    path = tmp_path / "p.yaml"
    path.write_text(GOOD)
    plan = make_plan(str(path), ["params.n=5", "nodes.plus.map.delta=[7]", "nodes.tot.cache=recompute"], str(tmp_path))
    assert plan.instances[0].params.n == 5
    assert [i.id for i in plan.instances] == ["src", "plus[delta=7]", "tot"]
    assert plan.instances[-1].runs and plan.instances[-1].reason == "cache: recompute"
    assert make_plan(str(path), ["src.scale=2.5"], str(tmp_path)).instances[0].params.scale == 2.5
    assert make_plan(str(path), ["n=7"], str(tmp_path)).instances[0].params.n == 7
    assert error_of(tmp_path, GOOD, ["deltaz=[1]"]).startswith("-S deltaz=[1]: unknown path 'deltaz'; did you mean 'deltas'?")
    assert error_of(tmp_path, GOOD, ["params.m=1"]) == "-S params.m=1: params has no key 'm' (keys: n, deltas)"
    assert error_of(tmp_path, GOOD, ["nodes.plsu.params.delta=1"]).startswith(
        "-S nodes.plsu.params.delta=1: nodes has no key 'plsu'; did you mean 'plus'?")
    assert error_of(tmp_path, GOOD, ["src.scael=2"]) == \
        "-S src.scael=2: node 'src' (t.source): unknown param 'scael'; did you mean 'scale'?"
    assert error_of(tmp_path, GOOD, ["params.n=[1"]).startswith("-S params.n=[1: VALUE is not valid YAML")
    assert error_of(tmp_path, GOOD, ["novalue"]).startswith("-S novalue: expected PATH=VALUE")


def test_overrides_replacing_nodes_or_params_by_a_value_are_refused(tmp_path, test_nodes):
    nodes_error = "'nodes:' must be a mapping of node name -> {type: ..., ...}"
    assert error_of(tmp_path, GOOD, ["nodes=5"]) == f"-S nodes=5: {nodes_error}"
    assert error_of(tmp_path, GOOD, ["nodes={}"]) == f"-S nodes={{}}: {nodes_error}"
    params_error = "'params:' must be a mapping of name -> value"
    assert error_of(tmp_path, GOOD, ["params=5"]) == f"-S params=5: {params_error}"
    assert error_of(tmp_path, GOOD, ["params=5", "n=3"]) == f"-S params=5: {params_error}"  # before the next one


def test_cli_reports_one_line_and_exit_code_2(tmp_path, cli, test_nodes):
    (tmp_path / "p.yaml").write_text(GOOD.replace('      n: "${n}"', '      nn: "${n}"'))
    result = cli("run", "p.yaml")
    assert result.returncode == 2
    assert result.stderr.strip() == "retrotouch: error: p.yaml:8:7: node 'src' (t.source): unknown param 'nn'; " \
                                    "did you mean 'n'?"
    assert "Traceback" not in result.stderr + result.stdout
    result = cli("run", "p.yaml", "-S", "params.nn=3")
    assert result.returncode == 2 and result.stderr.count("\n") == 1 and "did you mean 'n'" in result.stderr
    result = cli("run", "missing.yaml")
    assert result.returncode == 2 and result.stderr.strip() == \
        "retrotouch: error: cannot read pipeline missing.yaml: No such file or directory"


SEVERAL = GOOD.replace('''  tot:
    type: t.sum
    inputs: {xs: "plus[*]"}
''', '''  times:
    type: t.add
    inputs: {x: src}
    map: {delta: [10, 20, 30]}
  tot:
    type: t.sum
    inputs: {xs: ["plus[*]", "times[*]"]}
''')


def test_a_list_of_fan_ins_hands_every_branch_in_the_order_written(tmp_path, test_nodes):
    path = tmp_path / "p.yaml"
    path.write_text(SEVERAL)
    plan = make_plan(str(path), [], str(tmp_path))
    tot = plan.instances[-1]
    assert [u.id for u, _ in tot.inputs["xs"]] == ["plus[delta=1]", "plus[delta=2]", "times[delta=10]",
                                                   "times[delta=20]", "times[delta=30]"]
    swapped = SEVERAL.replace('["plus[*]", "times[*]"]', '["times[*]", "plus[*]"]')
    path.write_text(swapped)
    assert make_plan(str(path), [], str(tmp_path)).instances[-1].key != tot.key


def test_a_list_of_inputs_must_fan_in_each(tmp_path, test_nodes):
    msg = error_of(tmp_path, SEVERAL.replace('["plus[*]", "times[*]"]', '["plus[*]", "times"]'))
    assert msg.startswith("p.yaml:19:30: node 'tot': input 'xs' lists several nodes, so each must fan in: write times[*]")
    msg = error_of(tmp_path, SEVERAL.replace('["plus[*]", "times[*]"]', '["plus[*]", "tims[*]"]'))
    assert "input 'xs' refers to unknown node 'tims'; did you mean 'times'?" in msg
    assert "lists no node" in error_of(tmp_path, SEVERAL.replace('["plus[*]", "times[*]"]', "[]"))


PER = SEVERAL.replace("inputs: {x: src}\n    map: {delta: [10, 20, 30]}", "inputs: {x: plus}\n    map: {delta: [10, 20, 30]}") \
    .replace('inputs: {xs: ["plus[*]", "times[*]"]}', 'inputs: {xs: "times[*]"}\n    per: [plus]')
"""Each ``tot`` sums the three ``times`` branches of one ``plus`` branch (``times`` follows ``plus``)."""


def test_per_makes_one_reduce_per_branch_of_a_node_it_takes_no_data_from(tmp_path, test_nodes):
    path = tmp_path / "p.yaml"
    path.write_text(PER)
    plan = make_plan(str(path), [], str(tmp_path / "cache"))
    totals = [i for i in plan.instances if i.node == "tot"]
    assert [i.id for i in totals] == ["tot[delta=1]", "tot[delta=2]"]
    assert [[u.id for u, _ in t.inputs["xs"]] for t in totals] == [
        [f"times[plus.delta=1,times.delta={d}]" for d in (10, 20, 30)],
        [f"times[plus.delta=2,times.delta={d}]" for d in (10, 20, 30)]]
    assert set(totals[0].inputs) == {"xs"}  # plus's output is not an input
    wider = make_plan(str(path), ["deltas=[1, 2, 5]"], str(tmp_path / "cache"))
    assert [i.key for i in wider.instances if i.node == "tot"][:2] == [t.key for t in totals]  # a new branch leaves the others' keys
    run_pipeline(str(path), out_dir=str(tmp_path / "out"), cache_dir=str(tmp_path / "cache"), scheduler="sync")
    ran = make_plan(str(path), [], str(tmp_path / "cache"))
    sums = [ran.store.load(i.cached) for i in ran.instances if i.node == "tot"]
    # per plus branch, over times's 3 branches: sum(src) + 3 plus's delta + 3 times's delta, src = 0, 1, 2
    assert sums == [3 * (3 + 3 * 1) + 3 * (10 + 20 + 30), 3 * (3 + 3 * 2) + 3 * (10 + 20 + 30)]


def test_earlier_branches_fan_in_what_the_fan_in_handed_the_branches_before(tmp_path, test_nodes):
    path = tmp_path / "p.yaml"
    path.write_text(PER.replace('inputs: {xs: "times[*]"}', 'inputs: {xs: ["times[<]", "times[*]"]}'))
    plan = make_plan(str(path), [], str(tmp_path / "cache"))
    totals = [i for i in plan.instances if i.node == "tot"]
    first, second = ([f"times[plus.delta={p},times.delta={d}]" for d in (10, 20, 30)] for p in (1, 2))
    assert [[u.id for u, _ in t.inputs["xs"]] for t in totals] == [first, first + second]
    wider = make_plan(str(path), ["deltas=[1, 2, 5]"], str(tmp_path / "cache"))
    assert [i.key for i in wider.instances if i.node == "tot"][:2] == [t.key for t in totals]  # a later branch changes no key
    assert len([i for i in wider.instances if i.node == "tot"][2].inputs["xs"]) == 9
    alone = make_plan(str(path), ["deltas=[2]"], str(tmp_path / "cache"))
    assert [i.key for i in alone.instances if i.node == "tot"] != [totals[1].key]  # nothing before it now
    run_pipeline(str(path), out_dir=str(tmp_path / "out"), cache_dir=str(tmp_path / "cache"), scheduler="sync")
    ran = make_plan(str(path), [], str(tmp_path / "cache"))
    sums = [ran.store.load(i.cached) for i in ran.instances if i.node == "tot"]
    one = [3 * (3 + 3 * p) + 3 * (10 + 20 + 30) for p in (1, 2)]  # as in the per test above
    assert sums == [one[0], one[0] + one[1]]
    assert "[<]" in to_mermaid(ran.pipeline)


def test_earlier_branches_need_a_node_with_branches(tmp_path, test_nodes):
    msg = error_of(tmp_path, GOOD.replace('inputs: {xs: "plus[*]"}', 'inputs: {xs: "plus[<]"}'))
    assert msg.endswith("node 'tot': input 'xs' fans in plus[<], the branches before this node's own, but this node "
                        "has no branches; write [*]")
    msg = error_of(tmp_path, GOOD.replace('inputs: {xs: "plus[*]"}', 'inputs: {xs: "plus[>]"}'))
    assert "must be 'node', 'node.output', either with [*] or [<]" in msg


def test_per_must_name_nodes_and_cannot_make_a_cycle(tmp_path, test_nodes):
    assert error_of(tmp_path, PER.replace("per: [plus]", "per: [pluss]")).startswith(
        "p.yaml:20:11: node 'tot': per refers to unknown node 'pluss'; did you mean 'plus'?")
    assert "per must be a list of node names" in error_of(tmp_path, PER.replace("per: [plus]", "per: plus"))
    assert "cycle: plus -> tot -> times -> plus" in error_of(
        tmp_path, PER.replace("inputs: {x: src}\n    map: {delta", "inputs: {x: src}\n    per: [tot]\n    map: {delta"))
