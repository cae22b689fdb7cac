"""Cache keys: stable across processes, sensitive to exactly what they should be."""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

from retrotouch.graph.codeversion import normalised_source_hash
from retrotouch.graph.hashing import digest_fields, instance_key
from retrotouch.graph.runner import make_plan

SWEEP = """\
params:
  scales: [1, 2, 3]
nodes:
  src:  {type: t.source, map: {scale: "${scales}"}, params: {n: 3}}
  plus: {type: t.add, inputs: {x: src}, params: {delta: 0.5}}
  tot:  {type: t.sum, inputs: {xs: "plus[*]"}}
  out:  {type: t.write, inputs: {value: tot}}
"""

KEYS_SCRIPT = """
import json, sys
from retrotouch.graph.app import configure
from retrotouch.graph.runner import make_plan
from retrotouch.nodes.app import APP
configure(APP)
plan = make_plan(sys.argv[1], [], sys.argv[2])
print(json.dumps({i.id: i.key for i in plan.instances}))
"""


def write(tmp_path: Path, text: str, name: str = "p.yaml") -> str:
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def test_length_prefix_separates_fields():
    assert digest_fields(["ab", "c"]) != digest_fields(["a", "bc"])
    assert digest_fields(["ab", "c"]) == digest_fields([b"ab", b"c"])


def test_keys_identical_in_separate_processes(tmp_path, test_nodes):
    pipeline = write(tmp_path, SWEEP)
    here = {i.id: i.key for i in make_plan(pipeline, [], str(tmp_path / "cache")).instances}
    seen = []
    for seed in ("1", "12345"):
        out = subprocess.run([sys.executable, "-c", KEYS_SCRIPT, pipeline, str(tmp_path / "cache")],
                             capture_output=True, text=True, check=True,
                             env={**__import__("os").environ, "PYTHONHASHSEED": seed})
        seen.append(json.loads(out.stdout))
    assert seen[0] == seen[1] == here
    assert len(set(here.values())) == len(here) == 3 + 3 + 1 + 1


def test_param_change_changes_that_node_and_descendants_only(tmp_path, test_nodes):
    pipeline = write(tmp_path, SWEEP)
    before = {i.id: i.key for i in make_plan(pipeline, [], str(tmp_path)).instances}
    after = {i.id: i.key for i in make_plan(pipeline, ["nodes.plus.params.delta=0.75"], str(tmp_path)).instances}
    changed = sorted(k for k in before if before[k] != after[k])
    assert changed == ["out", "plus[scale=1]", "plus[scale=2]", "plus[scale=3]", "tot"]


def test_equivalent_params_give_the_same_key(tmp_path, test_nodes):
    """Defaults written out or omitted, ints for floats: the validated params are what is hashed."""
    a = write(tmp_path, "nodes:\n  s: {type: t.source, params: {n: 4, scale: 1}}\n", "a.yaml")
    b = write(tmp_path, "nodes:\n  s: {type: t.source, params: {scale: 1.0}}\n", "b.yaml")
    assert make_plan(a, [], str(tmp_path)).instances[0].key == make_plan(b, [], str(tmp_path)).instances[0].key


def test_extending_a_map_keeps_the_existing_branch_keys(tmp_path, test_nodes):
    pipeline = write(tmp_path, SWEEP)
    before = {i.id: i.key for i in make_plan(pipeline, [], str(tmp_path)).instances}
    after = {i.id: i.key for i in make_plan(pipeline, ["params.scales=[3, 1, 2, 4]"], str(tmp_path)).instances}
    for branch in ("src[scale=1]", "src[scale=2]", "src[scale=3]", "plus[scale=2]"):
        assert before[branch] == after[branch]
    assert before["tot"] != after["tot"]


def test_instance_key_depends_on_input_keys_and_code():
    base = dict(node_name="n", node_type="t", branch={}, code_version="c1", params_json="{}", file_hashes=[],
                inputs={"x": [("k1", "out")]})
    key = instance_key(**base)
    assert instance_key(**{**base, "inputs": {"x": [("k2", "out")]}}) != key
    assert instance_key(**{**base, "code_version": "c2"}) != key
    assert instance_key(**{**base, "inputs": {"y": [("k1", "out")]}}) != key


def test_code_version_ignores_comments_and_docstrings_but_not_code():
    src = textwrap.dedent('''
        def f(x):
            """Doc."""
            return x + 1  # comment
    ''')
    same = textwrap.dedent('''
        def f(x):
            # a different comment, no docstring
            return x + 1
    ''')
    other = src.replace("x + 1", "x + 2")
    assert normalised_source_hash(src) == normalised_source_hash(same)
    assert normalised_source_hash(src) != normalised_source_hash(other)


def test_the_code_version_memo_gives_the_same_versions_and_is_what_a_rerun_reads(tmp_path, monkeypatch):
    from retrotouch.graph import codeversion
    from retrotouch.graph.app import user_cache_dir
    from retrotouch.graph.registry import load

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    spec = load(["layout.screen"])["layout.screen"]
    monkeypatch.setattr(codeversion, "_module_cache", {})
    fresh = codeversion.code_version(spec)
    memo: dict = {}
    monkeypatch.setattr(codeversion, "_module_cache", {})
    assert codeversion.code_version(spec, memo) == fresh and len(memo) >= 5  # screen, sweep, selection, ...
    codeversion.save_memo(memo)
    again = codeversion.load_memo()
    assert again == memo
    monkeypatch.setattr(codeversion, "_module_cache", {})
    assert codeversion.code_version(spec, again) == fresh and len(again) == len(memo)  # all hits, nothing added
    key = next(iter(again))
    again[key] = ["0" * 64, again[key][1]]  # a memo entry is what is read: a wrong one changes the version
    monkeypatch.setattr(codeversion, "_module_cache", {})
    assert codeversion.code_version(spec, again) != fresh
    (Path(user_cache_dir()) / codeversion.MEMO_NAME).write_text("not json")
    assert codeversion.load_memo() == {}
    again[key] = "garbage"  # an entry of the wrong shape is recomputed
    monkeypatch.setattr(codeversion, "_module_cache", {})
    assert codeversion.code_version(spec, again) == fresh


def test_a_fresh_cache_folder_reads_the_code_version_memo_an_earlier_run_left(tmp_path, monkeypatch):
    """The memo lives in the user's cache folder, not in a result cache: planning into a new cache
    folder parses no source that an earlier plan, into another folder, already parsed."""
    import ast

    from retrotouch.graph import codeversion

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "user"))
    pipeline = str(Path(__file__).resolve().parents[1] / "pipelines" / "retrofit.yaml")
    monkeypatch.setattr(codeversion, "_module_cache", {})
    first = make_plan(pipeline, [], str(tmp_path / "a"))
    assert (tmp_path / "user" / "retrotouch" / codeversion.MEMO_NAME).exists()
    parsed, parse = [], ast.parse
    monkeypatch.setattr(codeversion.ast, "parse", lambda *a, **k: parsed.append(1) or parse(*a, **k))
    monkeypatch.setattr(codeversion, "_module_cache", {})
    second = make_plan(pipeline, [], str(tmp_path / "b"))
    assert parsed == [] and [i.key for i in second.instances] == [i.key for i in first.instances]
