"""Projector-camera calibration with a checkerboard and gray-code structured light (Moreno & Taubin 2012).

Procedure per board pose: project full white (the camera finds the checkerboard corners), full black
and the gray-code stack (``cv2.structured_light.GrayCodePattern``: per column bit, MSB first, the
pattern then its inverse; then the row bits). Each camera pixel is decoded to the projector pixel
that lit it; a local homography fitted to the decoded pixels in a window around each corner maps
the corner into projector pixels. ``calibrateCamera`` then runs for the camera and for the
projector (treated as an inverse camera), and ``stereoCalibrate`` gives the rigid transform.

Conventions: see :mod:`retrotouch.nodes.projection.render` (OpenCV pinhole, mm, ``T_b_a``). The
stereo result maps camera to projector coordinates: ``X_proj = R @ X_cam + T`` (mm).
Images are single-channel uint8 or float arrays (height, width).
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np

from ...graph.errors import UserError

CALIBRATION_FORMAT = "retrotouch.procam_calibration/1"


@dataclasses.dataclass(frozen=True)
class DeviceIntrinsics:
    """Pinhole intrinsics of a camera or projector: ``K`` (3, 3) px, ``dist`` (5,) OpenCV coefficients."""

    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int


@dataclasses.dataclass(frozen=True)
class ProCamCalibration:
    """Camera + projector intrinsics and the camera-to-projector transform (``X_proj = R X_cam + T``, mm).

    The depth frames used for tracking must be registered to this camera (e.g. an Azure Kinect's
    depth transformed to its colour camera). ``rms_*`` are the reprojection errors in pixels.
    """

    camera: DeviceIntrinsics
    projector: DeviceIntrinsics
    R: np.ndarray  # (3, 3)
    T: np.ndarray  # (3,) mm
    rms_camera_px: float
    rms_projector_px: float
    rms_stereo_px: float

    @property
    def T_proj_cam(self) -> np.ndarray:
        """(4, 4) pose taking camera coordinates to projector coordinates."""
        out = np.eye(4)
        out[:3, :3] = self.R
        out[:3, 3] = self.T
        return out


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


# ---------------------------------------------------------------------------------------------
# Patterns


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


# ---------------------------------------------------------------------------------------------
# Decoding


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


# ---------------------------------------------------------------------------------------------
# Calibration


@dataclasses.dataclass(frozen=True)
class BoardCapture:
    """The camera images of one board pose: under white and black light and the gray-code stack."""

    white: np.ndarray
    black: np.ndarray
    stack: list[np.ndarray]


def calibrate_procam(
    captures: list[BoardCapture],
    board: BoardSpec,
    proj_width: int,
    proj_height: int,
    window_px: int = 47,
) -> ProCamCalibration:
    """Calibrate camera, projector and their transform from board captures (>= 3 usable poses)."""
    obj, cam_pts, proj_pts = [], [], []
    for cap in captures:
        corners = find_board_corners(cap.white, board)
        if corners is None:
            continue
        px, py, valid = decode_gray_code(cap.stack, proj_width, proj_height, cap.white, cap.black)
        pc = projector_corners(corners, px, py, valid, window_px)
        if pc is None:
            continue
        obj.append(board.object_points())
        cam_pts.append(corners.astype(np.float32))
        proj_pts.append(pc)
    if len(obj) < 3:
        raise UserError(
            f"only {len(obj)} of {len(captures)} board poses were usable (corners found and decoded): capture at least 3 with the whole board lit"
        )
    cam_size = (captures[0].white.shape[1], captures[0].white.shape[0])
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 200, 1e-9)
    cam_flags = cv2.CALIB_FIX_K3
    rms_cam, K_cam, d_cam, _, _ = cv2.calibrateCamera(obj, cam_pts, cam_size, None, None, flags=cam_flags, criteria=criteria)
    proj_flags = cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
    rms_proj, K_proj, d_proj, _, _ = cv2.calibrateCamera(
        obj, proj_pts, (proj_width, proj_height), None, None, flags=proj_flags, criteria=criteria
    )
    rms_stereo, K_cam, d_cam, K_proj, d_proj, R, T, _, _ = cv2.stereoCalibrate(
        obj,
        cam_pts,
        proj_pts,
        K_cam,
        d_cam,
        K_proj,
        d_proj,
        cam_size,
        flags=cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3,
        criteria=criteria,
    )
    return ProCamCalibration(
        camera=DeviceIntrinsics(K_cam, d_cam.ravel()[:5].copy(), cam_size[0], cam_size[1]),
        projector=DeviceIntrinsics(K_proj, d_proj.ravel()[:5].copy(), proj_width, proj_height),
        R=np.asarray(R, np.float64),
        T=np.asarray(T, np.float64).ravel(),
        rms_camera_px=float(rms_cam),
        rms_projector_px=float(rms_proj),
        rms_stereo_px=float(rms_stereo),
    )


# ---------------------------------------------------------------------------------------------
# Files


def _device_json(d: DeviceIntrinsics) -> dict:
    return {"K": d.K.tolist(), "dist": np.asarray(d.dist).ravel().tolist(), "width": d.width, "height": d.height}


def calibration_to_json(cal: ProCamCalibration) -> str:
    """The calibration file text (JSON, mm and pixels)."""
    return json.dumps(
        {
            "format": CALIBRATION_FORMAT,
            "units": "mm",
            "camera": _device_json(cal.camera),
            "projector": _device_json(cal.projector),
            "R_proj_cam": cal.R.tolist(),
            "T_proj_cam_mm": cal.T.tolist(),
            "rms_px": {"camera": cal.rms_camera_px, "projector": cal.rms_projector_px, "stereo": cal.rms_stereo_px},
        },
        indent=1,
    )


def save_calibration(cal: ProCamCalibration, path: Path) -> None:
    """Write the calibration as JSON."""
    Path(path).write_text(calibration_to_json(cal))


def load_calibration(path: Path) -> ProCamCalibration:
    """Read a calibration JSON file; UserError naming the problem when it is missing or malformed."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise UserError(f"cannot read calibration file {path}: {exc.strerror}; pass --calibration FILE") from exc
    except json.JSONDecodeError as exc:
        raise UserError(f"calibration file {path} is not JSON ({exc.msg}, line {exc.lineno}): re-save it") from exc
    if not isinstance(data, dict) or data.get("format") != CALIBRATION_FORMAT:
        raise UserError(f"{path} is not a {CALIBRATION_FORMAT} file: write it with save_calibration")

    def device(d: dict, name: str) -> DeviceIntrinsics:
        try:
            K = np.asarray(d["K"], np.float64)
            dist = np.asarray(d["dist"], np.float64).ravel()
            if K.shape != (3, 3) or dist.shape != (5,):
                raise ValueError("K must be 3x3 and dist 5 values")
            return DeviceIntrinsics(K, dist, int(d["width"]), int(d["height"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise UserError(f"{path}: bad '{name}' entry ({exc}): needs K (3x3), dist (5), width, height") from exc

    try:
        R = np.asarray(data["R_proj_cam"], np.float64)
        T = np.asarray(data["T_proj_cam_mm"], np.float64).ravel()
        rms = data["rms_px"]
        if R.shape != (3, 3) or T.shape != (3,):
            raise ValueError("R_proj_cam must be 3x3 and T_proj_cam_mm 3 values")
        return ProCamCalibration(
            camera=device(data["camera"], "camera"),
            projector=device(data["projector"], "projector"),
            R=R,
            T=T,
            rms_camera_px=float(rms["camera"]),
            rms_projector_px=float(rms["projector"]),
            rms_stereo_px=float(rms["stereo"]),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"{path}: malformed calibration ({exc}): re-run the calibration") from exc


def demo_rig(width: int = 1280, height: int = 720) -> ProCamCalibration:
    """A plausible rig (the known truth of synthetic runs): camera f = 0.78 w, projector f = 1.2 w,
    the projector 150 mm left of and 30 mm below the camera, turned 15 degrees towards it, both
    ``width`` x ``height``; a little radial distortion on each; about 550 mm to the work area.
    """
    from scipy.spatial.transform import Rotation

    f_cam, f_proj = 0.78 * width, 1.2 * width
    camera = DeviceIntrinsics(
        np.array([[f_cam, 0.0, width / 2 + 3.0], [0.0, f_cam, height / 2 - 2.0], [0.0, 0.0, 1.0]]),
        np.array([0.04, -0.08, 0.0, 0.0, 0.0]),
        width,
        height,
    )
    projector = DeviceIntrinsics(
        np.array([[f_proj, 0.0, width / 2], [0.0, f_proj, 0.58 * height], [0.0, 0.0, 1.0]]),
        np.array([0.02, 0.0, 0.0, 0.0, 0.0]),
        width,
        height,
    )
    R_cam_proj = Rotation.from_euler("y", 15.0, degrees=True).as_matrix()
    centre = np.array([-150.0, 30.0, 0.0])  # projector centre in camera coordinates (mm)
    R = R_cam_proj.T
    return ProCamCalibration(camera, projector, R, -R @ centre, 0.0, 0.0, 0.0)


# ---------------------------------------------------------------------------------------------
# Synthetic captures (known truth, for tests, benchmarks and dry runs)


def _apply_distortion(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """OpenCV (k1, k2, p1, p2, k3) distortion of normalised image coordinates (n, 2)."""
    k1, k2, p1, p2, k3 = np.asarray(dist, np.float64).ravel()[:5]
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=1)


class BoardCaptureSimulator:
    """Renders what the camera sees when the projector's patterns light a checkerboard (known truth).

    The board plane (z = 0 of the board frame, mm) has albedo 0.9 on white squares and on a border
    of one square, 0.2 on black squares, 0.05 off the board. Camera pixels are traced through the
    camera's distortion (rays computed once); board points are projected with the projector's
    distortion onto the nearest pattern pixel. The white image is supersampled ``supersample``^2
    times so corners are sub-pixel accurate. Intensity = 255 * albedo * (0.1 + 0.85 * pattern) +
    Gaussian noise of ``noise_sigma`` grey levels.
    """

    def __init__(
        self,
        truth: ProCamCalibration,
        board: BoardSpec,
        noise_sigma: float = 1.0,
        supersample: int = 2,
    ) -> None:
        self.truth, self.board, self.noise_sigma, self.supersample = truth, board, noise_sigma, supersample
        self.patterns = gray_code_patterns(truth.projector.width, truth.projector.height)
        self._rays = {ss: self._camera_rays(ss) for ss in {1, supersample}}

    def _camera_rays(self, ss: int) -> tuple[np.ndarray, np.ndarray]:
        """Sample positions (N, 2) px and their undistorted rays (N, 3) (z = 1), row-major, ``ss``^2 per pixel."""
        cam = self.truth.camera
        offs = (np.arange(ss) + 0.5) / ss - 0.5
        xs = (np.arange(cam.width)[:, None] + offs[None, :]).ravel()
        ys = (np.arange(cam.height)[:, None] + offs[None, :]).ravel()
        gx, gy = np.meshgrid(xs, ys)
        pix = np.stack([gx.ravel(), gy.ravel()], axis=1)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-9)
        rays = cv2.undistortPoints(pix.reshape(-1, 1, 2), cam.K, cam.dist, None, None, None, criteria).reshape(-1, 2)
        return pix, np.column_stack([rays, np.ones(len(rays))])

    def _trace(self, T_cam_board: np.ndarray, ss: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Board albedo, projector pixel and 'lit by the projector' flag for each (super)sample.

        Only samples inside the board's image bounding box are traced; the background beyond it is
        far away, albedo 0.05 and unlit.
        """
        board, proj, cam = self.board, self.truth.projector, self.truth.camera
        pix, rays = self._rays[ss]
        lo, hi = -2 * board.square_mm, (np.array([board.cols, board.rows]) + 1) * board.square_mm
        outline = np.array([[lo, lo, 0], [hi[0], lo, 0], [hi[0], hi[1], 0], [lo, hi[1], 0]], np.float64)
        ob, _ = cv2.projectPoints(outline, cv2.Rodrigues(T_cam_board[:3, :3])[0], T_cam_board[:3, 3], cam.K, cam.dist)
        (x0, y0), (x1, y1) = ob.reshape(-1, 2).min(0) - 3, ob.reshape(-1, 2).max(0) + 3
        sel = np.flatnonzero((pix[:, 0] >= x0) & (pix[:, 0] <= x1) & (pix[:, 1] >= y0) & (pix[:, 1] <= y1))
        T_board_cam = np.linalg.inv(T_cam_board)
        d = rays[sel] @ np.ascontiguousarray(T_board_cam[:3, :3].T)
        o = T_board_cam[:3, 3]
        s = -o[2] / d[:, 2]
        p = o + s[:, None] * d
        sq = np.floor(p[:, :2] / board.square_mm).astype(np.int64) + 1
        on_squares = (sq[:, 0] >= 0) & (sq[:, 0] <= board.cols) & (sq[:, 1] >= 0) & (sq[:, 1] <= board.rows)
        on_board = (p[:, 0] > lo) & (p[:, 0] < hi[0]) & (p[:, 1] > lo) & (p[:, 1] < hi[1])
        black_sq = on_squares & ((sq[:, 0] + sq[:, 1]) % 2 == 0)
        albedo = np.full(len(pix), 0.05)
        albedo[sel] = np.where(on_board, np.where(black_sq, 0.2, 0.9), 0.05)
        T_proj_board = self.truth.T_proj_cam @ T_cam_board
        q = p @ np.ascontiguousarray(T_proj_board[:3, :3].T) + T_proj_board[:3, 3]
        ahead = q[:, 2] > 1e-6
        xy = _apply_distortion(q[:, :2] / np.where(ahead, q[:, 2], 1.0)[:, None], proj.dist)
        u = np.rint(proj.K[0, 0] * xy[:, 0] + proj.K[0, 1] * xy[:, 1] + proj.K[0, 2]).astype(np.int64)
        v = np.rint(proj.K[1, 1] * xy[:, 1] + proj.K[1, 2]).astype(np.int64)
        lit_sel = on_board & ahead & (s > 0) & (u >= 0) & (u < proj.width) & (v >= 0) & (v < proj.height)
        lit = np.zeros(len(pix), bool)
        lit[sel] = lit_sel
        uv = np.zeros((len(pix), 2), np.int64)
        uv[sel] = np.stack([u, v], axis=1)
        return albedo, uv, lit

    def _shade(self, pattern: np.ndarray, traced: tuple, ss: int, rng: np.random.Generator) -> np.ndarray:
        albedo, uv, lit = traced
        cam = self.truth.camera
        light = np.zeros(len(albedo))
        light[lit] = pattern[uv[lit, 1], uv[lit, 0]] / 255.0
        img = 255.0 * albedo * (0.1 + 0.85 * light)
        img = img.reshape(cam.height, ss, cam.width, ss).mean(axis=(1, 3))
        return np.clip(img + rng.normal(0.0, self.noise_sigma, img.shape), 0, 255).astype(np.float32)

    def capture(self, T_cam_board: np.ndarray, seed: int = 0) -> BoardCapture:
        """The white, black and gray-code camera images for the board at pose ``T_cam_board``."""
        rng = np.random.default_rng(seed)
        white = self._shade(self.patterns[0], self._trace(T_cam_board, self.supersample), self.supersample, rng)
        traced = self._trace(T_cam_board, 1)
        black = self._shade(self.patterns[1], traced, 1, rng)
        stack = [self._shade(p, traced, 1, rng) for p in self.patterns[2:]]
        return BoardCapture(white=white, black=black, stack=stack)
