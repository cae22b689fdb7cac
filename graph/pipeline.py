"""YAML pipelines: parsing with line/column marks, ``-S`` overrides, interpolation, validation.

Format (see README.md for the full reference)::

    params:                      # pipeline-level values, used as ${name} in node params and maps
      diagonal_mm: 170
    nodes:
      load:   {type: mesh.load, params: {path: builtin:bunny}}
      scaled: {type: mesh.scale, inputs: {mesh: load}, params: {diagonal_mm: "${diagonal_mm}"}}
      sweep:  {type: mesh.remesh, inputs: {mesh: scaled}, map: {target_edge_mm: [2, 3, 4]}}
      pick:   {type: some.reduce, inputs: {meshes: "sweep[*]"}, cache: recompute}
      both:   {type: some.reduce, inputs: {meshes: ["sweep[*]", "other[*]"]}}   # several fan-ins, in order
      slow:   {type: some.reduce, inputs: {meshes: "sweep[*]"}, priority: 1}  # starts before ready priority-0 tasks
      each:   {type: some.reduce, inputs: {meshes: "fine[*]"}, per: [sweep]}  # one reduce per branch of sweep
      vs:     {type: some.reduce, inputs: {meshes: "fine[*]", before: "fine[<]"}, per: [sweep]}  # and the earlier branches'
    fallback:                    # optional: run again with more overrides when a result falls short (.fallback)
      when: {value: pick.score, above: 0.2}
      set: {nodes.sweep.map.target_edge_mm: [1, 2, 3, 4]}

Every problem is reported as one line ``file:line:col: message`` (or ``-S PATH=VALUE: message`` for
an override) through :class:`PipelineError`, a :class:`UserError`.
"""
from __future__ import annotations

import copy
import dataclasses
import difflib
import hashlib
import re
from typing import Any, Iterable

import yaml

from .app import current
from .errors import UserError
from .node import NodeSpec

Path = tuple[str | int, ...]
NODE_KEYS = ("type", "inputs", "params", "map", "cache", "priority", "per")
TOP_KEYS = ("params", "nodes", "fallback")
CACHE_MODES = ("default", "recompute", "disable")
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_\-]*$")
_REF = re.compile(r"^([A-Za-z_][A-Za-z0-9_\-]*)(?:\.([A-Za-z_][A-Za-z0-9_]*))?(\[\*\]|\[<\])?$")
_INTERP = re.compile(r"\$\{([^}]*)\}")


class PipelineError(UserError):
    """A pipeline problem, already prefixed with its location."""


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """``"; did you mean 'x'?"`` for the closest choice, or ``""``."""
    close = difflib.get_close_matches(word, list(choices), n=1, cutoff=0.6)
    return f"; did you mean {close[0]!r}?" if close else ""


@dataclasses.dataclass
class Document:
    """A parsed YAML document: plain data plus where each value and key came from."""

    file: str
    text_sha256: str
    data: Any
    marks: dict[Path, str]  # value locations
    key_marks: dict[Path, str]  # mapping-key locations (for "unknown key" errors)
    via: dict[Path, str] = dataclasses.field(default_factory=dict)  # ${} sites filled from an -S override

    def where(self, path: Path, key: bool = False) -> str:
        """Location of ``path`` (its key when ``key``), or of its nearest located ancestor; a value
        that came from an ``-S`` override through ``${}`` names the override first."""
        origin = next((self.via[path[:n]] for n in range(len(path), 0, -1) if path[:n] in self.via), None)
        if key and path in self.key_marks:
            site = self.key_marks[path]
        else:
            site = next((self.marks[path[:n]] for n in range(len(path), 0, -1) if path[:n] in self.marks),
                        self.marks.get((), f"{self.file}:1:1"))
        return f"{origin} (used at {site})" if origin and origin != site else site

    def fail(self, path: Path, message: str, key: bool = False) -> PipelineError:
        return PipelineError(f"{self.where(path, key)}: {message}")


def load_document(file: str) -> Document:
    """Parse a YAML file keeping ``file:line:col`` marks for every value and key."""
    try:
        with open(file, "rb") as f:
            raw = f.read()
    except OSError as exc:
        raise UserError(f"cannot read pipeline {file}: {exc.strerror}") from None
    marks: dict[Path, str] = {}
    key_marks: dict[Path, str] = {}

    def loc(mark: yaml.Mark) -> str:
        return f"{file}:{mark.line + 1}:{mark.column + 1}"

    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UserError(f"{file}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    loader = yaml.SafeLoader(text)
    try:
        root = loader.get_single_node()

        def convert(node: yaml.Node, path: Path) -> Any:
            marks[path] = loc(node.start_mark)
            if isinstance(node, yaml.MappingNode):
                out: dict[str, Any] = {}
                for knode, vnode in node.value:
                    if not isinstance(knode, yaml.ScalarNode):
                        raise PipelineError(f"{loc(knode.start_mark)}: mapping keys must be plain names")
                    key = knode.value
                    if key in out:
                        raise PipelineError(f"{loc(knode.start_mark)}: duplicate key {key!r} "
                                            f"(first at {key_marks[path + (key,)]})")
                    key_marks[path + (key,)] = loc(knode.start_mark)
                    out[key] = convert(vnode, path + (key,))
                return out
            if isinstance(node, yaml.SequenceNode):
                return [convert(v, path + (i,)) for i, v in enumerate(node.value)]
            return loader.construct_object(node, deep=True)

        data = convert(root, ()) if root is not None else None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = loc(mark) if mark else f"{file}:1:1"
        raise PipelineError(f"{where}: YAML syntax error: {exc.problem or exc.context}") from None
    finally:
        loader.dispose()
    doc = Document(file, hashlib.sha256(raw).hexdigest(), data, marks, key_marks)
    if not isinstance(data, dict):
        raise doc.fail((), "a pipeline is a mapping with 'nodes:' (and optionally 'params:')")
    for key in data:
        if key not in TOP_KEYS:
            raise doc.fail((key,), f"unknown top-level key {key!r}{did_you_mean(key, TOP_KEYS)} "
                                   f"(allowed: {', '.join(TOP_KEYS)})", key=True)
    _check_top_level(doc)
    return doc


def _check_top_level(doc: Document) -> None:
    """Refuse a ``nodes:`` that is not a non-empty mapping or a ``params:`` that is not a mapping
    (in the file or after an ``-S`` override); an empty ``params:`` becomes ``{}``."""
    data = doc.data
    if not isinstance(data.get("nodes"), dict) or not data["nodes"]:
        raise doc.fail(("nodes",), "'nodes:' must be a mapping of node name -> {type: ..., ...}")
    if not isinstance(data.setdefault("params", {}) or {}, dict):
        raise doc.fail(("params",), "'params:' must be a mapping of name -> value")
    data["params"] = data["params"] or {}


# -- interpolation -----------------------------------------------------------------------------
def interpolate(doc: Document, value: Any, path: Path) -> Any:
    """Replace ``${name}`` with pipeline params; a whole-string ``${name}`` keeps the value's type."""
    params = doc.data["params"]

    def lookup(name: str, at: Path) -> Any:
        if name not in params:
            raise doc.fail(at, f"unknown pipeline param ${{{name}}}{did_you_mean(name, params)}"
                               f" (defined: {', '.join(params) or 'none'})")
        origin = next((m for p, m in doc.marks.items() if p[:2] == ("params", name) and m.startswith("-S ")), None)
        if origin:
            doc.via[at] = origin
        return params[name]

    def walk(v: Any, at: Path) -> Any:
        if isinstance(v, str):
            whole = _INTERP.fullmatch(v)
            if whole:
                return copy.deepcopy(lookup(whole.group(1).strip(), at))
            return _INTERP.sub(lambda m: str(lookup(m.group(1).strip(), at)), v)
        if isinstance(v, list):
            return [walk(x, at + (i,)) for i, x in enumerate(v)]
        if isinstance(v, dict):
            return {k: walk(x, at + (k,)) for k, x in v.items()}
        return v

    return walk(value, path)


# -- declarations ------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class InputRef:
    """``node``, ``node.output`` or either with ``[*]`` (fan-in over the node's branches) or ``[<]``
    (fan-in over the branches that ``[*]`` hands to the consuming node's earlier branches)."""

    node: str
    output: str
    fan_in: bool
    earlier: bool  # ``[<]``
    path: Path  # where it is written, for messages


@dataclasses.dataclass
class NodeDecl:
    """One node of a pipeline, checked against its node type (params are validated per branch)."""

    name: str
    spec: NodeSpec
    inputs: dict[str, tuple[InputRef, ...]]  # one ref, or several fan-ins handed on as one list
    params: dict[str, Any]  # interpolated, not yet validated
    map: dict[str, list[Any]]  # param -> values (several keys: product, in the order written)
    cache: str
    path: Path
    priority: int = 0  # among tasks ready at once, higher starts first (a scheduling hint: no cache key)
    per: tuple[str, ...] = ()  # nodes whose branches this one follows without taking their data


@dataclasses.dataclass
class Pipeline:
    """A validated pipeline: declarations in topological order."""

    doc: Document
    nodes: dict[str, NodeDecl]
    overrides: list[str]
    fallback: Any = None  # a .fallback.Fallback, or None

    @property
    def file(self) -> str:
        return self.doc.file


def _expect(doc: Document, path: Path, value: Any, kind: type, what: str) -> Any:
    if not isinstance(value, kind):
        raise doc.fail(path, f"{what} must be a {'mapping' if kind is dict else kind.__name__}, "
                             f"got {type(value).__name__}")
    return value


def load_pipeline(file: str, overrides: Iterable[str] = (), registry: dict[str, NodeSpec] | None = None) -> Pipeline:
    """Parse, override, interpolate and validate a pipeline file.

    ``registry`` defaults to discovering the node types the file names.
    """
    from .fallback import declare_fallback
    from .overrides import apply_override

    doc = load_document(file)
    overrides = list(overrides)
    for override in overrides:
        apply_override(doc, override)
        _check_top_level(doc)
    raw_nodes: dict[str, Any] = doc.data["nodes"]
    if registry is None:
        from . import registry as discovery

        types = [n["type"] for n in raw_nodes.values() if isinstance(n, dict) and isinstance(n.get("type"), str)]
        registry = discovery.load(types)
    decls = {name: _declare(doc, name, body, registry) for name, body in raw_nodes.items()}
    _resolve_references(doc, decls)
    return Pipeline(doc, _toposort(doc, decls), overrides, declare_fallback(doc, decls))


def _declare(doc: Document, name: str, body: Any, registry: dict[str, NodeSpec]) -> NodeDecl:
    """One node's declaration: its keys, type, inputs, params and map checked."""
    path: Path = ("nodes", name)
    if not _NAME.match(name):
        raise doc.fail(path, f"node name {name!r} must be letters, digits, '_' or '-'", key=True)
    _expect(doc, path, body, dict, f"node {name!r}")
    for key in body:
        if key not in NODE_KEYS:
            raise doc.fail(path + (key,), f"node {name!r}: unknown key {key!r}{did_you_mean(key, NODE_KEYS)}"
                                          f" (allowed: {', '.join(NODE_KEYS)})", key=True)
    if "type" not in body:
        raise doc.fail(path, f"node {name!r} has no 'type:'", key=True)
    type_name = body["type"]
    if not isinstance(type_name, str) or type_name not in registry:
        hint = did_you_mean(str(type_name), registry) or f" (list them with `{current().name} nodes`)"
        raise doc.fail(path + ("type",), f"node {name!r}: unknown node type {type_name!r}{hint}")
    spec = registry[type_name]
    inputs = _declare_inputs(doc, name, spec, body.get("inputs"))
    params = interpolate(doc, _expect(doc, path + ("params",), body.get("params") or {}, dict,
                                      f"node {name!r}: params"), path + ("params",))
    mapped = _declare_map(doc, name, spec, params, body.get("map"))
    cache = body.get("cache", "default")
    if cache not in CACHE_MODES:
        raise doc.fail(path + ("cache",), f"node {name!r}: cache must be one of {', '.join(CACHE_MODES)}"
                                          f"{did_you_mean(str(cache), CACHE_MODES)}")
    priority = body.get("priority", 0)
    if not isinstance(priority, int) or isinstance(priority, bool):
        raise doc.fail(path + ("priority",), f"node {name!r}: priority must be a whole number (higher starts first "
                                             f"among tasks ready at once; default 0), got {priority!r}")
    per = body.get("per", [])
    if not isinstance(per, list) or not all(isinstance(n, str) for n in per):
        raise doc.fail(path + ("per",), f"node {name!r}: per must be a list of node names (one instance per "
                                        f"branch of theirs), got {per!r}")
    return NodeDecl(name, spec, inputs, params, mapped, cache, path, priority, tuple(per))


def _declare_inputs(doc: Document, name: str, spec: NodeSpec, raw: Any) -> dict[str, tuple[InputRef, ...]]:
    path: Path = ("nodes", name)
    inputs_raw = _expect(doc, path + ("inputs",), raw or {}, dict, f"node {name!r}: inputs")
    inputs: dict[str, tuple[InputRef, ...]] = {}
    for input_name, ref_value in inputs_raw.items():
        ipath = path + ("inputs", input_name)
        if input_name not in spec.inputs:
            allowed = ", ".join(spec.inputs) or "none"
            raise doc.fail(ipath, f"node {name!r} ({spec.name}): unknown input {input_name!r}"
                                  f"{did_you_mean(input_name, spec.inputs)} (inputs: {allowed})", key=True)
        several = isinstance(ref_value, list)
        refs = []
        for i, ref_text in enumerate(ref_value if several else [ref_value]):
            rpath = ipath + (i,) if several else ipath
            m = _REF.match(ref_text) if isinstance(ref_text, str) else None
            if not m:
                raise doc.fail(rpath, f"node {name!r}: input {input_name!r} must be 'node', 'node.output', "
                                      f"either with [*] or [<], or a list of fan-ins, got {ref_text!r}")
            if several and not m.group(3):
                raise doc.fail(rpath, f"node {name!r}: input {input_name!r} lists several nodes, so each must "
                                      f"fan in: write {ref_text}[*]")
            if m.group(3) and spec.takes_one_value(input_name):
                raise doc.fail(rpath, f"node {name!r} ({spec.name}): input {input_name!r} takes one value, but "
                                      f"{ref_text} hands it a list of every branch: write {ref_text[:-3]} (the node "
                                      "then runs once per branch), or feed the list to a node that takes one")
            refs.append(InputRef(m.group(1), m.group(2) or "", bool(m.group(3)), m.group(3) == "[<]", rpath))
        if not refs:
            raise doc.fail(ipath, f"node {name!r}: input {input_name!r} lists no node")
        inputs[input_name] = tuple(refs)
    for input_name in spec.inputs:
        if input_name not in inputs:
            raise doc.fail(path, f"node {name!r} ({spec.name}): input {input_name!r} is not connected; "
                                 f"add inputs: {{{input_name}: <node>}}", key=True)
    return inputs


def _declare_map(doc: Document, name: str, spec: NodeSpec, params: dict[str, Any], raw: Any) -> dict[str, list[Any]]:
    path: Path = ("nodes", name)
    fields = spec.params.model_fields
    map_raw = _expect(doc, path + ("map",), raw or {}, dict, f"node {name!r}: map")
    mapped: dict[str, list[Any]] = {}
    for key, values in map_raw.items():
        mpath = path + ("map", key)
        if key not in fields:
            raise doc.fail(mpath, f"node {name!r} ({spec.name}): cannot map over unknown param {key!r}"
                                  f"{did_you_mean(key, fields)}", key=True)
        if key in params:
            raise doc.fail(mpath, f"node {name!r}: param {key!r} is both set in params and mapped; "
                                  "keep one", key=True)
        values = interpolate(doc, values, mpath)
        if not isinstance(values, list):
            raise doc.fail(mpath, f"node {name!r}: map {key!r} needs a list of values ([] for no branch), "
                                  f"got {values!r}")
        for i, value in enumerate(values):
            if value in values[:i]:
                raise doc.fail(mpath + (i,), f"node {name!r}: map {key!r} repeats the value {value!r}; "
                                             "list each value once")
        mapped[key] = values
    return mapped


def _resolve_references(doc: Document, decls: dict[str, NodeDecl]) -> None:
    """Check every input names an existing node and output; fill in the output of one-output nodes."""
    for decl in decls.values():
        for input_name, refs in decl.inputs.items():
            resolved = []
            for ref in refs:
                if ref.node not in decls:
                    raise doc.fail(ref.path, f"node {decl.name!r}: input {input_name!r} refers to unknown node "
                                             f"{ref.node!r}{did_you_mean(ref.node, decls)}")
                outputs = decls[ref.node].spec.outputs
                if ref.output and ref.output not in outputs:
                    raise doc.fail(ref.path, f"node {ref.node!r} has no output {ref.output!r}"
                                             f"{did_you_mean(ref.output, outputs)} (outputs: {', '.join(outputs)})")
                if not ref.output and len(outputs) != 1:
                    raise doc.fail(ref.path, f"node {ref.node!r} has outputs {', '.join(outputs)}; "
                                             f"write {ref.node}.<output>")
                resolved.append(ref if ref.output else dataclasses.replace(ref, output=outputs[0]))
            decl.inputs[input_name] = tuple(resolved)
        for i, other in enumerate(decl.per):
            if other not in decls:
                raise doc.fail(decl.path + ("per", i), f"node {decl.name!r}: per refers to unknown node {other!r}"
                                                       f"{did_you_mean(other, decls)}")


def _toposort(doc: Document, decls: dict[str, NodeDecl]) -> dict[str, NodeDecl]:
    order: dict[str, NodeDecl] = {}
    state: dict[str, int] = {}  # 1 visiting, 2 done

    def visit(name: str, trail: list[str]) -> None:
        if state.get(name) == 2:
            return
        state[name] = 1
        decl = decls[name]
        upstream = [(ref.node, ref.path) for refs in decl.inputs.values() for ref in refs]
        for node, path in upstream + [(n, decl.path + ("per", i)) for i, n in enumerate(decl.per)]:
            if state.get(node) == 1:
                chain = trail + [name]
                cycle = chain[chain.index(node):] + [node]
                raise doc.fail(path, f"cycle: {' -> '.join(cycle)}")
            visit(node, trail + [name])
        state[name] = 2
        order[name] = decls[name]

    for name in decls:
        visit(name, [])
    return order
