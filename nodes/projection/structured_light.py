"""Structured light for projector-camera calibration: patterns, gray-code decoding, board corners.

Procedure per board pose: project full white (the camera finds the checkerboard corners), full black
and the gray-code stack (``cv2.structured_light.GrayCodePattern``: per column bit, MSB first, the
pattern then its inverse; then the row bits). Each camera pixel is decoded to the projector pixel
that lit it; a local homography fitted to the decoded pixels in a window around each corner maps
the corner into projector pixels (Moreno & Taubin 2012). Images are single-channel uint8 or float
arrays (height, width); conventions: :mod:`.camera`.
"""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from ...graph.errors import UserError


@dataclasses.dataclass(frozen=True)
class BoardSpec:
    """A printed checkerboard: ``cols`` x ``rows`` inner corners, ``square_mm`` square side."""

    cols: int = 9
    rows: int = 7
    square_mm: float = 20.0

    def object_points(self) -> np.ndarray:
        """(cols * rows, 3) float32 inner-corner positions in the board frame (z = 0), row-major."""
        gx, gy = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        pts = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1) * self.square_mm
        return pts.astype(np.float32)


def gray_code_patterns(proj_width: int, proj_height: int) -> list[np.ndarray]:
    """The projector sequence: full white, full black, then the gray-code stack (uint8 images)."""
    pattern = cv2.structured_light.GrayCodePattern.create(proj_width, proj_height)
    ok, stack = pattern.generate()
    if not ok:
        raise UserError(f"cannot generate gray codes for a {proj_width}x{proj_height} projector: check its size")
    white = np.full((proj_height, proj_width), 255, np.uint8)
    return [white, np.zeros_like(white), *[np.asarray(p) for p in stack]]


def checkerboard_image(board: BoardSpec, square_px: int, border_px: int | None = None) -> np.ndarray:
    """A printable uint8 checkerboard with ``cols + 1`` x ``rows + 1`` squares and a white border."""
    border = square_px if border_px is None else border_px
    cells = (np.add.outer(np.arange(board.rows + 1), np.arange(board.cols + 1)) % 2 == 0)
    img = np.where(np.kron(cells, np.ones((square_px, square_px), bool)), 0, 255).astype(np.uint8)
    return np.pad(img, border, constant_values=255)


def decode_gray_code(
    stack: list[np.ndarray] | np.ndarray,
    proj_width: int,
    proj_height: int,
    white: np.ndarray,
    black: np.ndarray,
    black_threshold: float = 40.0,
    white_threshold: float = 5.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decode captured gray-code images to projector pixels, vectorised over all camera pixels.

    ``stack`` is the captured gray-code sequence in projection order (no white/black).
    Returns ``(proj_x, proj_y, valid)``: int32 maps and a bool mask; a pixel is valid when it is lit
    (``white - black > black_threshold``), every bit pair differs by at least ``white_threshold``,
    and the code lies inside the projector.
    """
    n_col = int(np.ceil(np.log2(proj_width)))
    n_row = int(np.ceil(np.log2(proj_height)))
    imgs = np.asarray(stack, np.float32)
    if imgs.shape[0] != 2 * (n_col + n_row):
        raise UserError(
            f"expected {2 * (n_col + n_row)} gray-code captures for a {proj_width}x{proj_height} projector, got {imgs.shape[0]}"
        )
    pos, neg = imgs[0::2], imgs[1::2]
    bits = pos > neg
    reliable = np.all(np.abs(pos - neg) >= white_threshold, axis=0)

    def to_binary(gray_bits: np.ndarray) -> np.ndarray:
        binary = np.logical_xor.accumulate(gray_bits, axis=0)
        weights = (1 << np.arange(len(gray_bits) - 1, -1, -1)).astype(np.int32)
        return np.tensordot(weights, binary.astype(np.int32), axes=1)

    proj_x = to_binary(bits[:n_col])
    proj_y = to_binary(bits[n_col:])
    lit = white.astype(np.float32) - black.astype(np.float32) > black_threshold
    valid = lit & reliable & (proj_x < proj_width) & (proj_y < proj_height)
    return proj_x.astype(np.int32), proj_y.astype(np.int32), valid


def find_board_corners(image: np.ndarray, board: BoardSpec) -> np.ndarray | None:
    """Sub-pixel inner corners (cols * rows, 2) float32 in the camera image, or None if not found."""
    img = np.clip(image, 0, 255).astype(np.uint8)
    found, corners = cv2.findChessboardCorners(img, (board.cols, board.rows), flags=cv2.CALIB_CB_ADAPTIVE_THRESH)
    if not found:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    corners = cv2.cornerSubPix(img, corners, (7, 7), (-1, -1), criteria)
    return corners.reshape(-1, 2)


def projector_corners(
    cam_corners: np.ndarray,
    proj_x: np.ndarray,
    proj_y: np.ndarray,
    valid: np.ndarray,
    window_px: int = 47,
    min_pixels: int = 50,
) -> np.ndarray | None:
    """Map camera corners to projector pixels with a local homography per corner (Moreno & Taubin).

    The homography (camera -> projector, least squares) is fitted to the decoded pixels inside a
    ``window_px`` square centred on the corner. Returns (n, 2) float32, or None when a window holds
    fewer than ``min_pixels`` decoded pixels.
    """
    half = window_px // 2
    h, w = valid.shape
    out = np.empty((len(cam_corners), 2), np.float32)
    for i, (cx, cy) in enumerate(cam_corners):
        x0, x1 = max(int(round(cx)) - half, 0), min(int(round(cx)) + half + 1, w)
        y0, y1 = max(int(round(cy)) - half, 0), min(int(round(cy)) + half + 1, h)
        win = valid[y0:y1, x0:x1]
        if win.sum() < min_pixels:
            return None
        ys, xs = np.nonzero(win)
        src = np.stack([xs + x0, ys + y0], axis=1).astype(np.float64)
        dst = np.stack([proj_x[y0:y1, x0:x1][win], proj_y[y0:y1, x0:x1][win]], axis=1).astype(np.float64)
        H, _ = cv2.findHomography(src, dst, 0)
        if H is None:
            return None
        p = H @ np.array([cx, cy, 1.0])
        out[i] = p[:2] / p[2]
    return out
