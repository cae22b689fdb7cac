"""Node declaration: a plain function plus a pydantic ``Params`` model.

A node type is declared with :func:`node`::

    class Params(NodeParams):
        target_edge_mm: float = Field(1.5, gt=0, description="remesh edge length (mm)")

    @node("mesh.remesh", params=Params, inputs=("mesh",), outputs=("mesh",))
    def remesh(params: Params, mesh: Mesh) -> Mesh:
        ...

Conventions (the engine relies on them):

* The function is called as ``func(params, **inputs)``; ``inputs`` are keyword arguments named as
  declared. A fan-in input (``node[*]`` in YAML) receives a ``list`` in branch order.
* One declared output: the function returns that value. Several outputs: it returns a ``dict``
  keyed by the declared output names.
* Values passed between nodes are plain data that :mod:`.artifacts` can store without pickle:
  ``None``/bool/int/float/str, lists/tuples/dicts of those, numpy arrays (non-object dtype), numpy
  scalars, frozen dataclasses defined in the app's node packages whose fields are such values, and
  :class:`Files` (what sink nodes return).
* ``note=f`` makes ``f(output value)`` (a one-line string, or None) the node's note on what it
  decided: the engine stores it with the cached value and shows it in the run summary (table and
  ``--json``) and in ``manifest.json`` whether the node ran or was a cache hit.
* Sink nodes (``sink=True``) return :class:`Files`; the engine writes them into the run's output
  folder atomically and lists them in ``manifest.json``.
* The code version is the sha256 of the AST-normalised source (docstrings and comments dropped) of
  the node's module and of every module of the app's node packages it imports, transitively (the
  engine excepted: engine changes bump the cache-format salt instead); pass ``version="..."`` to
  pin it by hand instead.
* Discovery: every module of the app's node packages (:mod:`.registry`) is imported by the engine;
  keep module imports cheap (heavy libraries inside the functions). Modules outside them are added
  with ``<APP>_NODE_MODULES=mod1,mod2``.
* A node that reads files names them in ``Params.input_files()``; their content is part of the
  cache key.
"""
from __future__ import annotations

import dataclasses
import types
import typing
from typing import Any, Callable

from pydantic import BaseModel, ConfigDict


class NodeParams(BaseModel):
    """Base of every node's ``Params``: unknown keys are rejected, instances are immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    def input_files(self) -> list[str]:
        """Paths of files this node reads, resolved as the node will resolve them.

        The engine hashes their *content* into the cache key, so editing a mesh file on disk
        reruns the node even though its params did not change. Override in nodes that read files.
        """
        return []


@dataclasses.dataclass(frozen=True)
class Files:
    """Files produced by a sink node: relative POSIX path inside the output folder -> content."""

    contents: dict[str, bytes]


@dataclasses.dataclass(frozen=True)
class NodeSpec:
    """A registered node type."""

    name: str
    func: Callable[..., Any]
    params: type[NodeParams]
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    version: str | None
    sink: bool
    doc: str
    note: Callable[[Any], str | None] | None = None

    def takes_one_value(self, input_name: str) -> bool:
        """Whether the function's annotation of ``input_name`` is known and admits no ``list`` (the
        value a ``node[*]`` fan-in hands over); False when unannotated or unresolvable."""
        try:
            hint = typing.get_type_hints(self.func).get(input_name)
        except Exception:  # noqa: BLE001 - an annotation that does not resolve says nothing
            return False
        if hint is None:
            return False
        members = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType) else (hint,)
        for member in members:
            origin = typing.get_origin(member) or member
            if member is Any or not isinstance(origin, type) or issubclass(list, origin):
                return False
        return True

    def note_of(self, value: Any) -> str | None:
        """The node's one-line note on its output ``value`` (``note=`` of :func:`node`), or None."""
        text = self.note(value) if self.note else None
        if text is not None and (not isinstance(text, str) or "\n" in text):
            raise TypeError(f"node {self.name}: note must be a one-line string or None, got {text!r}")
        return text


REGISTRY: dict[str, NodeSpec] = {}


class _NoParams(NodeParams):
    """No parameters."""


def node(
    name: str,
    *,
    params: type[NodeParams] | None = None,
    inputs: tuple[str, ...] = (),
    outputs: tuple[str, ...] = ("out",),
    version: str | None = None,
    sink: bool = False,
    note: Callable[[Any], str | None] | None = None,
) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Register ``func`` as node type ``name`` (dotted, e.g. ``"mesh.load"``); returns it unchanged.
    ``note(output value)`` gives the run summary's one-line note (module docstring)."""

    def register(func: Callable[..., Any]) -> Callable[..., Any]:
        if name in REGISTRY and REGISTRY[name].func.__qualname__ != func.__qualname__:
            raise ValueError(f"node type {name!r} is declared twice")
        if sink and outputs != ("files",):
            raise ValueError(f"sink node {name!r} must declare outputs=('files',)")
        REGISTRY[name] = NodeSpec(
            name=name,
            func=func,
            params=params or _NoParams,
            inputs=tuple(inputs),
            outputs=tuple(outputs),
            version=version,
            sink=sink,
            doc=(func.__doc__ or "").strip(),
            note=note,
        )
        return func

    return register
