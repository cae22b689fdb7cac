"""Planning: expand a pipeline into node instances (branches), validate params, compute cache keys
and decide, before anything runs, which instances are cache hits and which must run.

Branches: a node with ``map: {k: [...]}`` has one instance per value (several keys: their product,
in the order written). Each mapped key is an *axis*. A node inherits the axes of its plain inputs
(so downstream nodes are mapped branch-wise; inputs mapped over different axes combine as a
product) and a fan-in input ``x[*]`` receives, as a list in branch order, every branch of ``x``
along the axes the consuming node does not have itself. ``per: [y]`` gives a node ``y``'s axes
without its data (a fan-in then collects, per branch of ``y``, the branches that agree with it).
``x[<]`` receives what ``x[*]`` hands to the node's earlier branches (in branch order, each once):
nothing on the first branch, so a comparison running over a sweep (a second Tx pole's branches
against the first's) leaves the first branch's key as it was without the later ones. A
map over ``[]`` makes no branch: its node and every node mapped with it drop out of the run, and a
fan-in over them receives nothing from them.
"""
from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import os
from typing import Any

from pydantic import ValidationError

from .codeversion import code_version, load_memo, save_memo
from .errors import UserError
from .hashing import canonical_json, file_sha256, instance_key
from .node import NodeParams
from .pipeline import NodeDecl, Pipeline, did_you_mean
from .store import ArtifactRef, Store


@dataclasses.dataclass(frozen=True)
class Axis:
    owner: str  # the node whose map: declares it
    param: str
    values: tuple[Any, ...]

    @property
    def id(self) -> str:
        return f"{self.owner}.{self.param}"


@dataclasses.dataclass
class Instance:
    """One run of one pipeline node (one branch of a mapped node)."""

    decl: NodeDecl
    branch: dict[str, Any]  # axis id -> value
    label: str  # "angle_deg=10" ("" when the node is not mapped)
    params: NodeParams
    inputs: dict[str, list[tuple["Instance", str]]]  # input -> (upstream, output) pairs
    code_version: str
    file_hashes: list[tuple[str, str | None]]
    key: str
    cached: ArtifactRef | None = None  # the hit, if any
    runs: bool = False
    reason: str = ""  # why it runs (for --explain)

    @property
    def node(self) -> str:
        return self.decl.name

    @property
    def id(self) -> str:
        return f"{self.node}[{self.label}]" if self.label else self.node

    @property
    def type_name(self) -> str:
        return self.decl.spec.name

    @property
    def is_sink(self) -> bool:
        return self.decl.spec.sink

    @property
    def params_dump(self) -> dict[str, Any]:
        """The validated params as JSON data."""
        return self.params.model_dump(mode="json")


@dataclasses.dataclass
class Plan:
    pipeline: Pipeline
    instances: list[Instance]  # topological order
    store: Store

    @property
    def to_run(self) -> list[Instance]:
        return [i for i in self.instances if i.runs]

    @property
    def file(self) -> str:
        return self.pipeline.file

    @property
    def text_sha256(self) -> str:
        return self.pipeline.doc.text_sha256

    @property
    def overrides(self) -> list[str]:
        return self.pipeline.overrides


def _format_value(v: Any) -> str:
    return v if isinstance(v, str) else json.dumps(v, separators=(",", ":"))


def _validate(pipeline: Pipeline, decl: NodeDecl, raw: dict[str, Any], mapped_index: dict[str, int]) -> NodeParams:
    doc, spec = pipeline.doc, decl.spec
    try:
        return spec.params.model_validate(raw)
    except ValidationError as exc:
        err = exc.errors()[0]
    loc = err.get("loc") or ()
    field = str(loc[0]) if loc else ""
    fields = spec.params.model_fields
    what = f"node {decl.name!r} ({spec.name})"
    if err["type"] == "extra_forbidden":
        hint = did_you_mean(field, fields) or f" (params: {', '.join(fields) or 'none'})"
        raise doc.fail(decl.path + ("params", field), f"{what}: unknown param {field!r}{hint}", key=True)
    if err["type"] == "missing":
        raise doc.fail(decl.path + ("params",), f"{what}: missing required param {field!r}")
    if field in mapped_index:
        path = decl.path + ("map", field, mapped_index[field])
    else:
        path = decl.path + ("params",) + tuple(loc)
    if not field:  # a model validator, about the params together: named by an -S override among them, if any
        params_path = decl.path + ("params",)
        below = [p for p in (*doc.via, *doc.marks)
                 if len(p) > len(params_path) and p[:len(params_path)] == params_path]
        overridden = next((p for p in below if p in doc.via or doc.marks[p].startswith("-S ")), path)
        raise doc.fail(overridden, f"{what}: params: {err['msg'].removeprefix('Value error, ')}")
    got = f" (got {err['input']!r})" if "input" in err else ""
    raise doc.fail(path, f"{what}: param {field!r}: {err['msg']}{got}")


def _file_hashes(params: NodeParams, decl: NodeDecl, pipeline: Pipeline) -> list[tuple[str, str | None]]:
    try:
        paths = list(params.input_files())
    except UserError as exc:
        raise pipeline.doc.fail(decl.path + ("params",), f"node {decl.name!r}: {exc}") from None
    return [(p, file_sha256(p) if os.path.isfile(p) else None) for p in paths]


def expand(pipeline: Pipeline, store: Store) -> Plan:
    """All instances with their keys and hit/miss status (nothing runs)."""
    doc = pipeline.doc
    axes: dict[str, list[Axis]] = {}
    by_branch: dict[str, dict[tuple[int, ...], Instance]] = {}
    ordered: list[Instance] = []
    versions: dict[str, str] = {}
    memo = load_memo()
    known = len(memo)
    for name, decl in pipeline.nodes.items():
        inherited: list[Axis] = []
        followed = [ref.node for refs in decl.inputs.values() for ref in refs if not ref.fan_in] + list(decl.per)
        for upstream in followed:
            inherited += [a for a in axes[upstream] if a not in inherited]
        for input_name, ref in ((n, r) for n, refs in decl.inputs.items() for r in refs):
            if ref.earlier and not (inherited or decl.map):
                raise doc.fail(ref.path, f"node {name!r}: input {input_name!r} fans in {ref.node}[<], the branches "
                                         "before this node's own, but this node has no branches; write [*]")
            if ref.fan_in and not ref.earlier and not [a for a in axes[ref.node] if a not in inherited]:
                raise doc.fail(ref.path, f"node {name!r}: input {input_name!r} fans in {ref.node}[*], but "
                                         f"{ref.node!r} has no branches beyond this node's own; drop [*]")
        own = [Axis(name, k, tuple(v)) for k, v in decl.map.items()]
        node_axes = inherited + own
        axes[name] = node_axes
        short = {a.id: a.param if sum(b.param == a.param for b in node_axes) == 1 else a.id for a in node_axes}
        if decl.spec.name not in versions:
            try:
                versions[decl.spec.name] = code_version(decl.spec, memo)
            except (OSError, ValueError, SyntaxError) as exc:
                raise UserError(f"cannot compute the code version of node type {decl.spec.name}: {exc}") from None
        by_branch[name] = {}
        handed: dict[tuple[str, int], list[tuple[Instance, str]]] = {}  # what [*] gave the earlier branches, per [<] ref
        for idx in itertools.product(*(range(len(a.values)) for a in node_axes)):
            branch = {a.id: a.values[i] for a, i in zip(node_axes, idx)}
            raw = dict(decl.params)
            raw.update({a.param: a.values[i] for a, i in zip(node_axes, idx) if a.owner == name})
            params = _validate(pipeline, decl, raw, {a.param: i for a, i in zip(node_axes, idx) if a.owner == name})
            inputs: dict[str, list[tuple[Instance, str]]] = {}
            for input_name, refs in decl.inputs.items():
                inputs[input_name] = []
                for i, ref in enumerate(refs):
                    if ref.earlier:
                        before = handed.setdefault((input_name, i), [])
                        inputs[input_name] += before
                        seen = {(id(u), out) for u, out in before}
                        before += [(u, out) for u, out in _upstream(ref, axes, node_axes, idx, by_branch)
                                   if (id(u), out) not in seen]
                    else:
                        inputs[input_name] += _upstream(ref, axes, node_axes, idx, by_branch)
            label = ",".join(f"{short[a.id]}={_format_value(v)}" for a, v in zip(node_axes, branch.values()))
            files = _file_hashes(params, decl, pipeline)
            key = instance_key(
                node_name=name, node_type=decl.spec.name, branch=branch, code_version=versions[decl.spec.name],
                params_json=canonical_json(params.model_dump(mode="json")), file_hashes=[list(f) for f in files],
                inputs={n: [(u.key, out) for u, out in ups] for n, ups in inputs.items()})
            inst = Instance(decl, branch, label, params, inputs, versions[decl.spec.name], files, key)
            by_branch[name][idx] = inst
            ordered.append(inst)
    if len(memo) != known:
        save_memo(memo)
    plan = Plan(pipeline, ordered, store)
    _decide(plan)
    return plan


def _upstream(ref, axes: dict[str, list[Axis]], node_axes: list[Axis], idx: tuple[int, ...],
              by_branch: dict[str, dict[tuple[int, ...], Instance]]) -> list[tuple[Instance, str]]:
    """The ``(instance, output)`` pairs ``ref`` hands to the branch ``idx`` of a node with ``node_axes``:
    the upstream branch on the same axes values, or with ``[*]`` (and ``[<]``) every branch that agrees on
    the shared axes."""
    up_axes = axes[ref.node]
    if not ref.fan_in:
        return [(by_branch[ref.node][tuple(idx[node_axes.index(a)] for a in up_axes)], ref.output)]
    fixed = {up_axes.index(a): idx[node_axes.index(a)] for a in up_axes if a in node_axes}
    return [(inst, ref.output) for up_idx, inst in by_branch[ref.node].items()
            if all(up_idx[p] == v for p, v in fixed.items())]


def restrict(plan: Plan, targets: list[str]) -> Plan:
    """The plan of only ``targets`` (pipeline node names; every branch) and what they need; only
    the sinks among them write into the output folder."""
    nodes = plan.pipeline.nodes
    for target in targets:
        if target not in nodes:
            raise UserError(f"--target {target!r}: no such node{did_you_mean(target, nodes)} "
                            f"(nodes: {', '.join(nodes)})")
    keep: set[int] = set()
    for inst in reversed(plan.instances):
        if inst.node in targets or id(inst) in keep:
            keep.add(id(inst))
            keep.update(id(u) for ups in inst.inputs.values() for u, _ in ups)
    return refresh(Plan(plan.pipeline, [i for i in plan.instances if id(i) in keep], plan.store))


def refresh(plan: Plan) -> Plan:
    """The plan with what runs decided afresh against the cache (after other runs filled it); keys
    and params as planned."""
    for inst in plan.instances:
        inst.runs, inst.reason, inst.cached = False, "", None
    _decide(plan)
    return plan


def _decide(plan: Plan) -> None:
    """Mark what runs: misses, ``cache: recompute``, and ``cache: disable`` nodes whose output is needed."""
    for inst in plan.instances:
        mode = inst.decl.cache
        if mode == "default":
            inst.cached = plan.store.lookup(inst.key)
            inst.runs = inst.cached is None
        elif mode == "recompute":
            inst.runs, inst.reason = True, "cache: recompute"
    needed: set[int] = set()
    for inst in reversed(plan.instances):
        if inst.decl.cache == "disable" and (inst.decl.spec.sink or id(inst) in needed):
            inst.runs, inst.reason = True, "cache: disable"
        if inst.runs:
            needed.update(id(u) for ups in inst.inputs.values() for u, _ in ups)


# -- explain -----------------------------------------------------------------------------------
def _index_path(plan: Plan) -> str:
    ident = hashlib.sha256(os.path.abspath(plan.file).encode()).hexdigest()[:16]
    stem = os.path.splitext(os.path.basename(plan.file))[0]
    return os.path.join(plan.store.local, "runs", f"{stem}-{ident}.json")


def _record(inst: Instance) -> dict[str, Any]:
    return {"key": inst.key, "code": inst.code_version, "params": inst.params.model_dump(mode="json"),
            "files": [list(f) for f in inst.file_hashes],
            "inputs": {n: [u.key for u, _ in ups] for n, ups in inst.inputs.items()}}


def explain(plan: Plan) -> None:
    """Fill ``reason`` of every instance that runs, comparing with the pipeline's last recorded run."""
    try:
        with open(_index_path(plan), encoding="utf-8") as f:
            previous = json.load(f)
    except (OSError, ValueError):
        previous = {}
    for inst in plan.to_run:
        if inst.reason:
            continue
        old = previous.get(inst.id)
        if old is None:
            inst.reason = "no previous run recorded"
            continue
        new = _record(inst)
        reasons = []
        if old["code"] != new["code"]:
            reasons.append("code changed")
        changed = sorted(k for k in set(old["params"]) | set(new["params"])
                         if old["params"].get(k, object()) != new["params"].get(k, object()))
        if changed:
            reasons.append("params changed: " + ", ".join(changed))
        if old.get("files") != new["files"]:
            reasons.append("input files changed")
        inputs = sorted(k for k in set(old["inputs"]) | set(new["inputs"]) if old["inputs"].get(k) != new["inputs"].get(k))
        if inputs:
            reasons.append("inputs changed: " + ", ".join(inputs))
        inst.reason = "; ".join(reasons) or "cache entry missing (cleared, collected or corrupt)"


def record_run(plan: Plan) -> None:
    """Remember what each instance ran with (compared against by the next ``--explain``)."""
    path = _index_path(plan)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    tmp = f"{path}.{os.getpid()}.tmp"
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump({inst.id: _record(inst) for inst in plan.instances}, f, indent=1, sort_keys=True)
    os.replace(tmp, path)
