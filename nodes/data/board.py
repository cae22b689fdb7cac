"""The Muca board (FT5316 touch controller) as the host sees it, stated once for the project.

A frame is ``NUM_TX x NUM_RX`` raw mutual-capacitance counts (0..``MAX_COUNT``), TX-major: the cell
of channels ``(tx, rx)`` sits at wire index ``tx * NUM_RX + rx``. A layout may wire fewer channels.
"""
from __future__ import annotations

import math

NUM_TX = 21  # drive (Tx) channels of the board
NUM_RX = 12  # sense (Rx) channels of the board
MAX_COUNT = 65535  # largest raw count (16-bit)


def default_coupling_width_mm(finger_radius_mm: float, pitch_mm: float) -> float:
    """Width ``s`` (mm) of the Gaussian coupling ``exp(-d^2 / (2 s^2))`` of a finger of contact
    radius ``finger_radius_mm`` over crossings ``pitch_mm`` apart: ``sqrt(r^2 + (pitch / 2)^2)``."""
    return float(math.hypot(finger_radius_mm, pitch_mm / 2))
