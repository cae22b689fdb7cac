"""Helpers shared by the sensing tests."""
from __future__ import annotations

from collections.abc import Iterable

import numpy as np


def parse_stream(chunks: Iterable[bytes], parser) -> list[np.ndarray]:
    """All frames a parser finds in a chunked byte stream, in order."""
    frames: list[np.ndarray] = []
    for chunk in chunks:
        frames.extend(parser.feed(chunk))
    return frames
