"""``fallback:``: a second, wider run of a pipeline when its first result falls short.

    fallback:
      when: {value: best.metrics.uncovered_share, above: 0.2}   # or below: ...
      set: {tx_poles: [far, centre]}                          # overrides, PATH: VALUE as for -S

A full run (no ``--target``) first runs ``when``'s node and what it needs, and reads the value: the
node's output (``node.output`` when it has several), then keys into mappings or attributes. When it
is above (below) the threshold, the pipeline is planned again with ``set`` added to the run's
overrides and that plan runs; otherwise the plan as it was. What the first part computed stays
cached, so the wider run computes only what ``set`` changes. ``when``'s node must have one branch;
``set``'s overrides are checked before anything runs; ``-S fallback=null`` turns the fallback off.
The run summary, ``run --json`` and the manifest say what was read and what was done (:meth:`Fallback.outcome`).
"""
from __future__ import annotations

import dataclasses
import json
import numbers
from typing import Any

from .errors import UserError
from .pipeline import Document, NodeDecl, did_you_mean

FALLBACK_KEYS = ("when", "set")
WHEN_KEYS = ("value", "above", "below")


@dataclasses.dataclass(frozen=True)
class Fallback:
    """A parsed ``fallback:`` (module docstring)."""

    node: str
    output: str | None  # None: the node has one output
    keys: tuple[str, ...]
    threshold: float
    above: bool  # True: falls short above the threshold; False: below it
    overrides: tuple[str, ...]  # ``PATH=VALUE`` (VALUE as JSON, which is YAML)
    where: str  # ``file:line:col`` of ``when.value``
    set_where: str  # ``file:line:col`` of ``set``

    @property
    def value_name(self) -> str:
        return self._name(self.keys)

    @property
    def side(self) -> str:
        return "above" if self.above else "below"

    def _name(self, keys: tuple[str, ...]) -> str:
        return ".".join([self.node, *([self.output] if self.output else []), *keys])

    def read(self, output: Any) -> float:
        """The value in the node's stored output (``output``); a missing key or a non-number is a UserError."""
        value = output[self.output] if self.output else output
        for depth, key in enumerate(self.keys):
            if isinstance(value, dict) and key in value:
                value = value[key]
            elif not isinstance(value, dict) and hasattr(value, key):
                value = getattr(value, key)
            else:
                known = list(value) if isinstance(value, dict) else list(getattr(value, "__dict__", {}))
                raise UserError(f"{self.where}: fallback value {self.value_name}: {self._name(self.keys[:depth])} has no {key!r}"
                                f"{did_you_mean(key, known)}; name a number in the node's output")
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise UserError(f"{self.where}: fallback value {self.value_name} is {type(value).__name__}, not a number")
        return float(value)

    def falls_short(self, value: float) -> bool:
        return value > self.threshold if self.above else value < self.threshold

    def outcome(self, value: float | None) -> dict[str, Any]:
        """What was read (None: the overrides change nothing, so nothing was) and done, with a summary line."""
        wider = value is not None and self.falls_short(value)
        if value is None:
            summary = f"its set changes nothing in this run ({' '.join(self.overrides)})"
        elif wider:
            summary = f"{self.value_name} is {value:.4g}, {self.side} {self.threshold:g}: ran again with {' '.join(self.overrides)}"
        else:
            summary = f"{self.value_name} is {value:.4g}, not {self.side} {self.threshold:g}: no second run"
        return {"value": self.value_name, "read": value, self.side: self.threshold, "set": list(self.overrides),
                "ran_again": wider, "summary": summary}


def declare_fallback(doc: Document, decls: dict[str, NodeDecl]) -> Fallback | None:
    """The pipeline's ``fallback:`` checked against its nodes, or None when it has none (or ``null``)."""
    raw = doc.data.get("fallback")
    if raw is None:
        return None
    path = ("fallback",)
    usage = "fallback: needs when: {value: NODE.OUTPUT.KEY, above: NUMBER (or below:)} and set: {PATH: VALUE}"
    if not isinstance(raw, dict):
        raise doc.fail(path, usage)
    _only_known_keys(doc, path, raw, FALLBACK_KEYS)
    for key in FALLBACK_KEYS:
        if not isinstance(raw.get(key), dict) or not raw[key]:
            raise doc.fail(path + (key,) if key in raw else path, usage)
    when, settings = raw["when"], raw["set"]
    _only_known_keys(doc, path + ("when",), when, WHEN_KEYS)
    sides = [k for k in ("above", "below") if k in when]
    if "value" not in when or len(sides) != 1:
        raise doc.fail(path + ("when",), usage + " (exactly one of above and below)")
    threshold = when[sides[0]]
    if isinstance(threshold, bool) or not isinstance(threshold, numbers.Real):
        raise doc.fail(path + ("when", sides[0]), f"fallback.when.{sides[0]} must be a number, got {threshold!r}")
    node, output, keys = _value_path(doc, path + ("when", "value"), when["value"], decls)
    overrides = tuple(f"{p}={json.dumps(v)}" for p, v in settings.items())
    return Fallback(node, output, keys, float(threshold), sides[0] == "above", overrides,
                    doc.where(path + ("when", "value")), doc.where(path + ("set",)))


def _only_known_keys(doc: Document, path: tuple, mapping: dict, allowed: tuple[str, ...]) -> None:
    for key in mapping:
        if key not in allowed:
            raise doc.fail(path + (key,), f"{'.'.join(path)}: unknown key {key!r}{did_you_mean(key, allowed)} "
                                          f"(allowed: {', '.join(allowed)})", key=True)


def _value_path(doc: Document, path: tuple, text: Any, decls: dict[str, NodeDecl]) -> tuple[str, str | None, tuple[str, ...]]:
    if not isinstance(text, str) or not text:
        raise doc.fail(path, f"fallback.when.value must be NODE.OUTPUT.KEY... (text), got {text!r}")
    node, *rest = text.split(".")
    if node not in decls:
        raise doc.fail(path, f"fallback.when.value: unknown node {node!r}{did_you_mean(node, decls)}")
    outputs = decls[node].spec.outputs
    if len(outputs) == 1:
        return node, None, tuple(rest[1:] if rest and rest[0] == outputs[0] else rest)
    if not rest or rest[0] not in outputs:
        raise doc.fail(path, f"fallback.when.value: node {node!r} has outputs {', '.join(outputs)}; "
                             f"write {node}.<output>.<key>")
    return node, rest[0], tuple(rest[1:])
