"""Node types for bench/engine.py: pure-Python CPU work that threads cannot parallelise.

Registered in benchmark runs through ``PYTHONPATH=bench`` and ``RETROTOUCH_NODE_MODULES=engine_nodes``
(dask workers started by the run inherit both).
"""
from __future__ import annotations

from pydantic import Field

from retrotouch.graph.node import NodeParams, node


class WorkParams(NodeParams):
    seed: int = Field(0, description="start value of the generator")
    iterations: int = Field(2_000_000, ge=1, description="loop iterations (pure Python, about 0.1 us each)")


@node("bench.python_work", params=WorkParams, outputs=("value",))
def python_work(params: WorkParams) -> int:
    """A linear congruential generator stepped ``iterations`` times in a Python loop (holds the GIL)."""
    x = params.seed
    acc = 0
    for _ in range(params.iterations):
        x = (1103515245 * x + 12345) & 0x7FFFFFFF
        acc ^= x
    return acc


class CollectParams(NodeParams):
    pass


@node("bench.collect", params=CollectParams, inputs=("parts",), outputs=("value",))
def collect(params: CollectParams, parts: list) -> int:
    """XOR of the branch results (fan-in)."""
    out = 0
    for p in parts:
        out ^= int(p)
    return out
