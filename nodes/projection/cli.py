"""``retrotouch project``: play a recorded or synthetic depth sequence and write the projector frames.

Usage::

    retrotouch project --layout RUN_FOLDER --calibration rig.json --frames DEPTH_DIR --out OUT
    retrotouch project --layout RUN_FOLDER --calibration rig.json --synthetic 90 --out OUT --video

``RUN_FOLDER`` is a run's output folder holding ``projection/<name>_scene.npz`` (written by the
``projection.textures`` sink) or that file itself. ``DEPTH_DIR`` holds 16-bit depth PNGs (mm)
registered to the calibrated camera. ``--synthetic N`` renders N frames of the object turning in
front of the calibrated camera (known truth; pose errors are reported). ``--mode lines`` (default)
projects the curves as 3D polylines; ``--mode texture`` renders the per-layer textures baked by the
sink onto the atlas mesh (perspective-correct UV interpolation).

Output: ``OUT/<layer>/frame_000000.png`` per layer (Tx first), optionally ``OUT/<layer>.mp4``, and
``OUT/track.json`` with the per-frame status, inlier fraction, residual and pose.

Calibration (before use)::

    retrotouch project-patterns --projector-size 1280x720 --out PATTERNS
    # show PATTERNS/00.png, 01.png, ... full screen on the projector; for each board pose save the
    # camera image of every pattern as CAPTURES/<pose>/00.png, 01.png, ... (same numbers)
    retrotouch project-calibrate --captures CAPTURES --projector-size 1280x720 --board 9x7 --square-mm 20 --out rig.json

Pattern 00 is full white (the camera finds the board corners under it), 01 full black, then the
gray codes; ``PATTERNS/board.png`` is a printable checkerboard with the given inner corners.
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import cv2
import numpy as np
import typer

from ...graph.errors import UserError
from ..data.types import Mesh
from ..data.scene import ProjectionScene, load_scene
from .calibration import BoardCapture, ProCamCalibration, calibrate_procam, load_calibration, save_calibration
from .depth_frames import DepthFolderSource, FrameSource, SyntheticDepthSource, demo_trajectory
from .raster import render_textured
from .render import render_layers
from .structured_light import BoardSpec, checkerboard_image, gray_code_patterns
from .tracking import DepthTracker, TrackResult, pose_error


def find_scene_file(layout: Path) -> Path:
    """The ``*_scene.npz`` of a run folder (or the file itself); UserError when absent or ambiguous."""
    if layout.is_file():
        return layout
    if not layout.is_dir():
        raise UserError(f"--layout {layout} does not exist: pass a run output folder")
    found = sorted(layout.glob("**/*_scene.npz"))
    if not found:
        raise UserError(f"no projection/*_scene.npz in {layout}: run a pipeline with the projection.textures sink first")
    if len(found) > 1:
        raise UserError(f"{len(found)} projection scenes in {layout}: pass one of them with --layout FILE")
    return found[0]


def make_source(
    scene: ProjectionScene,
    calibration: ProCamCalibration,
    frames: Optional[Path],
    synthetic: Optional[int],
    fps: float,
    noise_mm: float,
    distance_mm: float,
) -> tuple[FrameSource, Optional[np.ndarray]]:
    """The frame source and, for synthetic runs, the true poses."""
    if (frames is None) == (synthetic is None):
        raise UserError("pass exactly one of --frames DIR or --synthetic N")
    if frames is not None:
        if not frames.is_dir():
            raise UserError(f"--frames {frames} is not a folder of depth PNGs")
        return DepthFolderSource(frames, calibration.camera, fps), None
    if synthetic is None or synthetic < 1:
        raise UserError("--synthetic needs a frame count >= 1")
    poses = demo_trajectory(synthetic, distance_mm=distance_mm, fps=fps)
    mesh = Mesh(scene.vertices, scene.faces, "projection scene")
    return SyntheticDepthSource(mesh, calibration.camera, poses, noise_mm=noise_mm, fps=fps), poses


def projector_images(
    scene: ProjectionScene, cal: ProCamCalibration, T_cam_obj: Optional[np.ndarray], mode: str
) -> dict[str, np.ndarray]:
    """One projector image per layer for the object at ``T_cam_obj`` (all black while it is not found)."""
    proj = cal.projector
    if T_cam_obj is None:
        blank = np.zeros((proj.height, proj.width, 3), np.uint8)
        return {n: blank for n in scene.layer_names}
    T_proj_obj = cal.T_proj_cam @ T_cam_obj
    if mode == "texture":
        return {n: render_textured(scene, i, T_proj_obj, proj) for i, n in enumerate(scene.layer_names)}
    return render_layers(scene, T_proj_obj, proj)


def frame_record(index: int, result: TrackResult, T_true: Optional[np.ndarray]) -> dict:
    """The ``track.json`` entry of one frame (with the pose error when the true pose is known)."""
    rec = {
        "frame": index,
        "status": result.status,
        "inlier_fraction": round(result.inlier_fraction, 4),
        "rms_mm": round(result.rms_mm, 4) if np.isfinite(result.rms_mm) else None,
        "T_cam_obj": None if result.T_cam_obj is None else np.round(result.T_cam_obj, 6).tolist(),
    }
    if T_true is not None and result.T_cam_obj is not None:
        rec["error_deg"], rec["error_mm"] = (round(e, 4) for e in pose_error(result.T_cam_obj, T_true))
    return rec


def run_projection(
    layout: Path,
    calibration_file: Path,
    out: Path,
    frames: Optional[Path] = None,
    synthetic: Optional[int] = None,
    video: bool = False,
    fps: float = 30.0,
    noise_mm: float = 0.5,
    distance_mm: float = 550.0,
    mode: str = "lines",
) -> dict:
    """Track, render and write the projector frames; returns the summary written to ``track.json``."""
    if mode not in ("lines", "texture"):
        raise UserError(f"--mode {mode!r} is unknown: use lines or texture")
    scene = load_scene(find_scene_file(layout))
    if mode == "texture" and scene.atlas_uv is None:
        raise UserError("--mode texture needs a scene with baked textures: re-run the projection.textures sink")
    cal = load_calibration(calibration_file)
    source, truth = make_source(scene, cal, frames, synthetic, fps, noise_mm, distance_mm)
    tracker = DepthTracker(Mesh(scene.vertices, scene.faces, "projection scene"), cal.camera)
    proj = cal.projector
    try:
        out.mkdir(parents=True, exist_ok=True)
        for name in scene.layer_names:
            (out / name).mkdir(exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create output folder {out}: {exc.strerror}") from exc
    writers = {}
    if video:
        fourcc = cv2.VideoWriter_fourcc(*"mp4v")
        writers = {n: cv2.VideoWriter(str(out / f"{n}.mp4"), fourcc, fps, (proj.width, proj.height)) for n in scene.layer_names}
    records = []
    latencies = []
    try:
        for frame in source.frames():
            t0 = time.perf_counter()
            result = tracker.update(frame)
            images = projector_images(scene, cal, result.T_cam_obj, mode)
            latencies.append(time.perf_counter() - t0)
            for name, img in images.items():
                cv2.imwrite(str(out / name / f"frame_{frame.index:06d}.png"), img)
                if name in writers:
                    writers[name].write(img)
            records.append(frame_record(frame.index, result, None if truth is None else truth[frame.index]))
    finally:
        for w in writers.values():
            w.release()
    tracked = [r for r in records if r["status"] in ("found", "tracked")]
    summary = {
        "frames": len(records),
        "tracked": len(tracked),
        "layers": list(scene.layer_names),
        "median_latency_ms": round(1000 * float(np.median(latencies)), 2) if latencies else None,
        "records": records,
    }
    (out / "track.json").write_text(json.dumps(summary, indent=1))
    return summary


def project(
    layout: Path = typer.Option(..., "--layout", help="run output folder with projection/*_scene.npz (or that file)"),
    calibration: Path = typer.Option(..., "--calibration", help="projector-camera calibration JSON"),
    out: Path = typer.Option(..., "--out", help="output folder for the projector frames"),
    frames: Optional[Path] = typer.Option(None, "--frames", help="folder of 16-bit depth PNGs (mm) registered to the camera"),
    synthetic: Optional[int] = typer.Option(None, "--synthetic", help="render N synthetic depth frames instead"),
    video: bool = typer.Option(False, "--video", help="also write OUT/<layer>.mp4"),
    fps: float = typer.Option(30.0, "--fps", help="frame rate of the sequence and video"),
    noise_mm: float = typer.Option(0.5, "--noise-mm", help="synthetic depth noise (mm)"),
    distance_mm: float = typer.Option(550.0, "--distance-mm", help="synthetic object distance from the camera (mm)"),
    mode: str = typer.Option("lines", "--mode", help="lines: projected 3D polylines; texture: the baked per-layer textures"),
) -> None:
    """Track the object in depth frames and write the projector image per layer (Tx first)."""
    # Operator errors are raised as UserError; the retrotouch CLI prints them as one line, exit code 2.
    summary = run_projection(layout, calibration, out, frames, synthetic, video, fps, noise_mm, distance_mm, mode)
    typer.echo(
        f"{summary['frames']} frames ({summary['tracked']} tracked), layers {', '.join(summary['layers'])}, "
        f"median {summary['median_latency_ms']} ms/frame -> {out}"
    )


def parse_size(text: str, option: str) -> tuple[int, int]:
    """'1280x720' -> (1280, 720); UserError naming ``option`` otherwise."""
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.isdigit() and int(p) > 0 for p in parts):
        raise UserError(f"{option} {text!r} must look like 1280x720")
    return int(parts[0]), int(parts[1])


def project_patterns(
    projector_size: str = typer.Option(..., "--projector-size", help="projector resolution, e.g. 1280x720"),
    out: Path = typer.Option(..., "--out", help="folder for the pattern PNGs"),
    board: str = typer.Option("9x7", "--board", help="checkerboard inner corners, columns x rows"),
) -> None:
    """Write the calibration patterns to show on the projector (00 white, 01 black, gray codes) and a printable board."""
    width, height = parse_size(projector_size, "--projector-size")
    cols, rows = parse_size(board, "--board")
    patterns = gray_code_patterns(width, height)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create {out}: {exc.strerror}") from exc
    for i, img in enumerate(patterns):
        cv2.imwrite(str(out / f"{i:02d}.png"), img)
    cv2.imwrite(str(out / "board.png"), checkerboard_image(BoardSpec(cols, rows, 1.0), square_px=100))
    typer.echo(f"{len(patterns)} patterns for a {width}x{height} projector and board.png -> {out}")


def read_captures(folder: Path, count: int) -> list[BoardCapture]:
    """Board captures from ``folder/<pose>/NN.png`` (greyscale, NN = pattern number); UserError when incomplete."""
    if not folder.is_dir():
        raise UserError(f"--captures {folder} is not a folder")
    poses = sorted(p for p in folder.iterdir() if p.is_dir())
    if not poses:
        raise UserError(f"no pose folders in {folder}: save each board pose's images as {folder}/<pose>/00.png ...")
    captures = []
    for pose in poses:
        images = []
        for i in range(count):
            img = cv2.imread(str(pose / f"{i:02d}.png"), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise UserError(f"{pose / f'{i:02d}.png'} is missing or unreadable: each pose needs {count} images 00..{count - 1:02d}")
            images.append(img.astype(np.float32))
        captures.append(BoardCapture(white=images[0], black=images[1], stack=images[2:]))
    return captures


def project_calibrate(
    captures: Path = typer.Option(..., "--captures", help="folder with one sub-folder of camera images per board pose"),
    projector_size: str = typer.Option(..., "--projector-size", help="projector resolution, e.g. 1280x720"),
    out: Path = typer.Option(..., "--out", help="calibration JSON to write"),
    board: str = typer.Option("9x7", "--board", help="checkerboard inner corners, columns x rows"),
    square_mm: float = typer.Option(..., "--square-mm", help="checkerboard square side (mm)"),
) -> None:
    """Calibrate camera and projector from gray-code captures of a checkerboard and write the calibration JSON."""
    width, height = parse_size(projector_size, "--projector-size")
    cols, rows = parse_size(board, "--board")
    if square_mm <= 0:
        raise UserError("--square-mm must be positive")
    count = len(gray_code_patterns(width, height))
    cal = calibrate_procam(read_captures(captures, count), BoardSpec(cols, rows, square_mm), width, height)
    save_calibration(cal, out)
    typer.echo(
        f"RMS camera {cal.rms_camera_px:.3f} px, projector {cal.rms_projector_px:.3f} px, "
        f"stereo {cal.rms_stereo_px:.3f} px -> {out}"
    )


def register(app: typer.Typer) -> None:
    """Add the ``project``, ``project-patterns`` and ``project-calibrate`` commands to the retrotouch CLI."""
    app.command("project")(project)
    app.command("project-patterns")(project_patterns)
    app.command("project-calibrate")(project_calibrate)
