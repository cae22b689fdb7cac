"""Tiny node types for the engine tests (cheap, deterministic).

Subprocess runs see them through ``PYTHONPATH=tests/engine_nodes`` and
``RETROTOUCH_NODE_MODULES=rt_testnodes``; dask workers started from such a process inherit both.
"""
from __future__ import annotations

import json
import os
import time

import numpy as np
from pydantic import Field, model_validator

from retrotouch.graph.errors import UserError
from retrotouch.graph.node import Files, NodeParams, node


class SourceParams(NodeParams):
    n: int = Field(4, ge=1, description="number of values")
    scale: float = Field(1.0, description="multiplier")
    sleep_s: float = Field(0.0, ge=0, description="pause before returning (s), to make runs overlap")


@node("t.source", params=SourceParams, outputs=("values",))
def source(params: SourceParams) -> np.ndarray:
    """0, 1, ..., n-1 times scale."""
    time.sleep(params.sleep_s)
    return np.arange(params.n, dtype=np.float64) * params.scale


class AddParams(NodeParams):
    delta: float = Field(0.0, description="added to every value")


@node("t.add", params=AddParams, inputs=("x",), outputs=("y",))
def add(params: AddParams, x: np.ndarray) -> np.ndarray:
    """x + delta."""
    return x + params.delta


class NoParams(NodeParams):
    pass


@node("t.sum", params=NoParams, inputs=("xs",), outputs=("total",))
def total(params: NoParams, xs: list) -> float:
    """Sum of every value of every branch (fan-in)."""
    return float(sum(float(np.sum(x)) for x in xs))


@node("t.stats", params=NoParams, inputs=("x",), outputs=("mean", "count"))
def stats(params: NoParams, x: np.ndarray) -> dict:
    """Two outputs: mean and count."""
    return {"mean": float(np.mean(x)), "count": int(len(x))}


class WriteParams(NodeParams):
    filename: str = Field("value.json", description="file written into the output folder")


@node("t.write", params=WriteParams, inputs=("value",), outputs=("files",), sink=True)
def write(params: WriteParams, value) -> Files:
    """The input as JSON."""
    data = value.tolist() if isinstance(value, np.ndarray) else value
    return Files({params.filename: json.dumps(data).encode()})


class FailParams(NodeParams):
    kind: str = Field("user", description="user | crash")


@node("t.fail", params=FailParams, inputs=("x",), outputs=("y",))
def fail(params: FailParams, x: np.ndarray) -> np.ndarray:
    """Raises: a UserError (kind=user) or a ZeroDivisionError (kind=crash)."""
    if params.kind == "user":
        raise UserError("the input is unusable; pick another one")
    return x * (1 // 0)  # a genuine bug: ZeroDivisionError


class BlobParams(NodeParams):
    megabytes: float = Field(1.0, gt=0, description="size of the file written (MB)")


@node("t.blob", params=BlobParams, outputs=("files",), sink=True)
def blob(params: BlobParams) -> Files:
    """A file of zero bytes of the given size (for full-disk tests)."""
    return Files({"blob.bin": bytes(int(params.megabytes * 1e6))})


class RangeParams(NodeParams):
    low: float = Field(0.0, description="lower bound")
    high: float = Field(1.0, description="upper bound")

    @model_validator(mode="after")
    def ordered(self) -> "RangeParams":
        if self.high <= self.low:
            raise ValueError("high must be above low")
        return self


@node("t.range", params=RangeParams, outputs=("values",))
def value_range(params: RangeParams) -> np.ndarray:
    """low and high (a params model with a validator over two fields)."""
    return np.array([params.low, params.high])


class PidParams(NodeParams):
    branch: int = Field(0, description="only tells the branches apart")
    sleep_s: float = Field(0.0, ge=0, description="pause before returning (s), so that branches spread over workers")


@node("t.pid", params=PidParams, outputs=("pid",))
def worker_pid(params: PidParams) -> int:
    """The id of the process that ran this node."""
    time.sleep(params.sleep_s)
    return os.getpid()


@node("t.rows", params=NoParams, inputs=("xs",), outputs=("rows",))
def rows(params: NoParams, xs: list) -> list:
    """One record per fan-in branch: its index and the sum of its values."""
    return [{"index": i, "total": float(np.sum(x))} for i, x in enumerate(xs)]


@node("t.picture", params=NoParams, inputs=("value",), outputs=("files",), sink=True)
def picture(params: NoParams, value) -> Files:
    """An SVG image showing the value as text."""
    svg = (f'<svg xmlns="http://www.w3.org/2000/svg" width="200" height="40"><text x="5" y="25">{value}</text>'
           "</svg>")
    return Files({"picture.svg": svg.encode()})
