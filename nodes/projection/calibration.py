"""Projector-camera calibration from gray-code captures of a checkerboard (Moreno & Taubin 2012).

The board corners found under white light and mapped into projector pixels by
:mod:`.structured_light` feed ``calibrateCamera`` for the camera and for the projector (treated as
an inverse camera); ``stereoCalibrate`` then gives the rigid transform. Conventions: :mod:`.camera`.
The stereo result maps camera to projector coordinates: ``X_proj = R @ X_cam + T`` (mm).
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np

from ...graph.errors import UserError
from .camera import DeviceIntrinsics
from .structured_light import BoardSpec, decode_gray_code, find_board_corners, projector_corners

CALIBRATION_FORMAT = "retrotouch.procam_calibration/1"


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
        raise UserError(f"{path} is not a {CALIBRATION_FORMAT} file: write it with "
                        "`retrotouch project-calibrate ... --out FILE`")

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
