"""The pipeline graph as text: Mermaid (``flowchart``), Graphviz dot, and SVG through ``dot``.

One box per pipeline node (name, node type, and ``× N`` with the mapped params for a node with
branches), sinks drawn as documents, one edge per input labelled with its name (``[*]`` for a
fan-in, ``[<]`` for one over the earlier branches). ``states`` (node -> ``cached`` | ``ran`` |
``running`` | ``would run`` | ``failed`` ...) colours the boxes and adds the state to the label.
"""
from __future__ import annotations

import json
import shutil
import subprocess

from .errors import UserError
from .pipeline import Pipeline

FORMATS = ("mermaid", "dot", "svg")
STATE_COLOURS = {"cached": "#d9ead3", "ran": "#b6d7a8", "running": "#ffe599", "would run": "#fce5cd",
                 "failed": "#f4cccc", "skipped": "#eeeeee"}


def _branches(pipeline: Pipeline, name: str) -> int:
    count = 1
    for values in pipeline.nodes[name].map.values():
        count *= len(values)
    return count


def _label(pipeline: Pipeline, name: str, states: dict[str, str]) -> list[str]:
    decl = pipeline.nodes[name]
    lines = [name, decl.spec.name]
    if decl.map:
        lines.append(f"× {_branches(pipeline, name)} ({', '.join(decl.map)})")
    if name in states:
        lines.append(states[name])
    return lines


def _edges(pipeline: Pipeline) -> list[tuple[str, str, str]]:
    return [(ref.node, name, input_name + ("[<]" if ref.earlier else "[*]" if ref.fan_in else ""))
            for name, decl in pipeline.nodes.items() for input_name, refs in decl.inputs.items() for ref in refs]


def to_mermaid(pipeline: Pipeline, states: dict[str, str] | None = None) -> str:
    states = states or {}
    ids = {name: f"n{i}" for i, name in enumerate(pipeline.nodes)}
    out = ["flowchart TD"]
    for name, decl in pipeline.nodes.items():
        text = "<br/>".join(line.replace('"', "'") for line in _label(pipeline, name, states))
        out.append(f'  {ids[name]}[/"{text}"/]' if decl.spec.sink else f'  {ids[name]}["{text}"]')
    for up, down, label in _edges(pipeline):
        out.append(f"  {ids[up]} -->|{label}| {ids[down]}")
    for name in pipeline.nodes:
        if states.get(name) in STATE_COLOURS:
            out.append(f"  style {ids[name]} fill:{STATE_COLOURS[states[name]]}")
    return "\n".join(out) + "\n"


def to_dot(pipeline: Pipeline, states: dict[str, str] | None = None) -> str:
    states = states or {}
    out = ["digraph pipeline {", '  rankdir=TB; node [shape=box, style="rounded,filled", fillcolor="#ffffff", '
           'fontname="Helvetica"]; edge [fontname="Helvetica", fontsize=10];']
    for name, decl in pipeline.nodes.items():
        attrs = [f"label={json.dumps(chr(10).join(_label(pipeline, name, states)), ensure_ascii=False)}"]
        if decl.spec.sink:
            attrs.append('shape=note, style="filled"')
        if states.get(name) in STATE_COLOURS:
            attrs.append(f'fillcolor="{STATE_COLOURS[states[name]]}"')
        out.append(f"  {json.dumps(name)} [{', '.join(attrs)}];")
    for up, down, label in _edges(pipeline):
        out.append(f"  {json.dumps(up)} -> {json.dumps(down)} [label={json.dumps(label)}];")
    return "\n".join(out) + "\n}\n"


def to_svg(pipeline: Pipeline, states: dict[str, str] | None = None) -> str:
    """SVG drawn by Graphviz's ``dot`` (a UserError naming the fix when it is not installed)."""
    dot = shutil.which("dot")
    if dot is None:
        raise UserError("--format svg needs Graphviz's `dot` on PATH: install graphviz (e.g. apt-get install "
                        "graphviz) or use --format dot or mermaid")
    done = subprocess.run([dot, "-Tsvg"], input=to_dot(pipeline, states), capture_output=True, text=True, timeout=60)
    if done.returncode != 0:
        raise UserError(f"dot failed: {done.stderr.strip().splitlines()[0] if done.stderr.strip() else done.returncode}")
    return done.stdout


def render(pipeline: Pipeline, fmt: str, states: dict[str, str] | None = None) -> str:
    if fmt not in FORMATS:
        raise UserError(f"--format {fmt!r}: expected one of {', '.join(FORMATS)}")
    return {"mermaid": to_mermaid, "dot": to_dot, "svg": to_svg}[fmt](pipeline, states)
