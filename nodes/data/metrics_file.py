"""``metrics.json``: the layout's quality figures as a run reports them, with its one writer.

Specified by ``metrics.schema.json`` beside this module (format :data:`METRICS_FORMAT`). Lengths
are millimetres, areas mm², angles degrees (key suffixes ``_mm``, ``_mm2``, ``_deg``); CVs and
shares are plain ratios. The top level holds the chosen Rx-angle branch's figures, ``angles`` one
row per branch (the per-angle table), ``pose`` the resting pose the layout was made for, ``touch``
the finger model that decided what can be touched, ``ingest_repairs`` what mesh ingest changed in the file,
and ``limbs`` the object's limbs with the cells on each.
"""
from __future__ import annotations

import json

import numpy as np

METRICS_FORMAT = "retrotouch.metrics/1"
"""Bump with metrics.schema.json when a field changes meaning or goes."""


def metrics_json(metrics: dict, pose: dict, touch: dict, ingest_repairs: list[str], limbs: list[dict]) -> bytes:
    """The metrics.json bytes: format, the layout's metrics, the pose, the finger model, the ingest repairs
    and the limbs."""
    document = {"format": METRICS_FORMAT, **metrics, "pose": pose, "touch": touch, "ingest_repairs": list(ingest_repairs),
                "limbs": limbs}
    return json.dumps(document, indent=1, default=_json_default).encode()


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"metrics value of type {type(value).__name__} is not JSON serialisable")
