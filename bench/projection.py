"""Projection-guided assembly benchmark: calibration, tracking and projector rendering at 1280 x 720.

Known-truth synthetic scene: the rig ``demo_rig(1280, 720)`` is calibrated from simulated
gray-code captures of a checkerboard; the bunny (170 mm, ~20k faces) with a 21 x 12 plane-section
layout turns in front of the camera (90 frames at 30 fps, 0.5 mm depth noise, 1 mm quantisation);
every frame is tracked with the *estimated* camera and rendered (both layers) for the *estimated*
projector. Latency = tracking + rendering per frame (depth synthesis excluded), on 2 threads.
Pose error = a second tracker given the true camera intrinsics against the true poses (with the
estimated intrinsics the pose is relative to a slightly different camera; that bias is part of
the crossing error, which chains calibration, tracking and smoothing).
Crossing error = distance on the true surface between a crossing and where light from its
projected pixel lands in the true rig, for the smoothed pose that is projected.

The projection.textures sink (which bakes the scene's textures) is timed on the same bunny and layout.

Prints a table, then as its LAST line one JSON object.
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "2")

import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # synthetic scenes live with the tests

from proj_fixtures import bunny_layout, bunny_mm, bunny_regions, calibrate_synthetic, demo_rig, landing_points  # noqa: E402
from retrotouch.nodes.data.scene import build_scene  # noqa: E402
from retrotouch.nodes.projection.camera import project_points, transform_points  # noqa: E402
from retrotouch.nodes.projection.depth_frames import SyntheticDepthSource, demo_trajectory  # noqa: E402
from retrotouch.nodes.projection.raster import rasterize_depth  # noqa: E402
from retrotouch.nodes.projection.render import RenderStyle, render_layers, visible_points  # noqa: E402
from retrotouch.nodes.projection.textures import TextureParams, projection_textures  # noqa: E402
from retrotouch.nodes.projection.tracking import DepthTracker, pose_error  # noqa: E402


FRAMES = 90
CROSSING_EVERY = 10
CALIBRATION_POSES = 10


def crossing_errors(scene, mesh, T_est, T_true, est_projector, true_projector) -> np.ndarray:
    """Landing error (mm) of every crossing drawn for pose ``T_est`` when the true projector pose is ``T_true``."""
    zbuf = rasterize_depth(transform_points(T_est, mesh.vertices), mesh.faces, est_projector.K, est_projector.width, est_projector.height)
    vis = visible_points(scene.crossing_points, scene.crossing_normals, T_est, est_projector.K, zbuf, RenderStyle(), landmarks=True)
    pixels = project_points(transform_points(T_est, scene.crossing_points[vis]), est_projector)
    landed = landing_points(pixels, mesh.vertices, mesh.faces, T_true, true_projector)
    return np.linalg.norm(landed - scene.crossing_points[vis], axis=1)


def textures_sink_seconds(mesh, layout) -> float:
    """Best of 3 runs (s) of the projection.textures sink (default 2048 px texture), after one warm-up run."""
    regions = bunny_regions(mesh)
    projection_textures(TextureParams(), mesh, regions, layout)
    runs = []
    for _ in range(3):
        t0 = time.perf_counter()
        projection_textures(TextureParams(), mesh, regions, layout)
        runs.append(time.perf_counter() - t0)
    return min(runs)


def main() -> None:
    cv2.setNumThreads(2)
    truth = demo_rig(1280, 720)
    t0 = time.perf_counter()
    cal = calibrate_synthetic(truth, count=CALIBRATION_POSES)
    t_cal = time.perf_counter() - t0

    mesh = bunny_mm(10000)
    layout = bunny_layout(mesh, 21, 12)
    scene = build_scene(mesh, layout)
    poses = demo_trajectory(FRAMES, fps=30.0)
    tracker = DepthTracker(mesh, cal.camera)
    tracker_true_camera = DepthTracker(mesh, truth.camera)
    track_ms, render_ms, raw_err, smooth_err, cross = [], [], [], [], []
    init_ms = float("nan")
    statuses: dict[str, int] = {}
    for frame in SyntheticDepthSource(mesh, truth.camera, poses, noise_mm=0.5).frames():
        t1 = time.perf_counter()
        result = tracker.update(frame)
        t2 = time.perf_counter()
        render_layers(scene, cal.T_proj_cam @ result.T_cam_obj, cal.projector)
        t3 = time.perf_counter()
        statuses[result.status] = statuses.get(result.status, 0) + 1
        if frame.index == 0:
            init_ms = 1000 * (t2 - t1)
        else:
            track_ms.append(1000 * (t2 - t1))
            render_ms.append(1000 * (t3 - t2))
        reference = tracker_true_camera.update(frame)
        raw_err.append(pose_error(reference.raw_T_cam_obj, poses[frame.index]))
        smooth_err.append(pose_error(reference.T_cam_obj, poses[frame.index]))
        if frame.index % CROSSING_EVERY == 0:
            cross.append(
                crossing_errors(scene, mesh, cal.T_proj_cam @ result.T_cam_obj, truth.T_proj_cam @ poses[frame.index], cal.projector, truth.projector)
            )
    track_ms, render_ms = np.array(track_ms), np.array(render_ms)
    total = track_ms + render_ms
    raw_err, smooth_err = np.array(raw_err), np.array(smooth_err)
    cross_all = np.concatenate(cross)
    cross_all = cross_all[np.isfinite(cross_all)]
    textures_s = textures_sink_seconds(mesh, layout)

    print(f"projection benchmark: bunny {len(mesh.faces)} faces, layout {layout.tx.count} Tx x {layout.rx.count} Rx, "
          f"{len(layout.cells.points)} crossings, {FRAMES} frames at 1280x720, 2 threads")
    print(f"calibration: {CALIBRATION_POSES} synthetic board poses in {t_cal:.1f} s; RMS camera {cal.rms_camera_px:.3f} px, "
          f"projector {cal.rms_projector_px:.3f} px, stereo {cal.rms_stereo_px:.3f} px")
    print(f"global search (frame 0): {init_ms:.0f} ms; statuses {statuses}")
    print(f"{'stage':<22}{'median ms':>10}{'mean ms':>10}{'p95 ms':>10}")
    for name, arr in (("tracking (ICP)", track_ms), ("render tx+rx", render_ms), ("total per frame", total)):
        print(f"{name:<22}{np.median(arr):>10.1f}{arr.mean():>10.1f}{np.percentile(arr, 95):>10.1f}")
    print(f"{'error':<22}{'mean':>10}{'max':>10}")
    print(f"{'raw pose deg':<22}{raw_err[:, 0].mean():>10.3f}{raw_err[:, 0].max():>10.3f}")
    print(f"{'raw pose mm':<22}{raw_err[:, 1].mean():>10.3f}{raw_err[:, 1].max():>10.3f}")
    print(f"{'smoothed pose deg':<22}{smooth_err[:, 0].mean():>10.3f}{smooth_err[:, 0].max():>10.3f}")
    print(f"{'smoothed pose mm':<22}{smooth_err[:, 1].mean():>10.3f}{smooth_err[:, 1].max():>10.3f}")
    print(f"{'crossing landing mm':<22}{cross_all.mean():>10.3f}{cross_all.max():>10.3f}   ({len(cross_all)} drawn crossings)")
    print(f"projection.textures sink (GLB, OBJ, PNG, scene; 2048 px): {textures_s:.2f} s (best of 3)")
    print(json.dumps({
        "fps": round(1000.0 / float(np.median(total)), 1),
        "fps_mean": round(1000.0 / float(total.mean()), 1),
        "track_ms_median": round(float(np.median(track_ms)), 2),
        "render_ms_median": round(float(np.median(render_ms)), 2),
        "global_init_ms": round(init_ms, 0),
        "pose_error_deg": round(float(raw_err[:, 0].mean()), 4),
        "pose_error_mm": round(float(raw_err[:, 1].mean()), 4),
        "pose_error_deg_max": round(float(raw_err[:, 0].max()), 4),
        "pose_error_mm_max": round(float(raw_err[:, 1].max()), 4),
        "smoothed_pose_error_deg": round(float(smooth_err[:, 0].mean()), 4),
        "smoothed_pose_error_mm": round(float(smooth_err[:, 1].mean()), 4),
        "calibration_rms_px": round(max(cal.rms_camera_px, cal.rms_projector_px, cal.rms_stereo_px), 4),
        "crossing_error_mm": round(float(cross_all.mean()), 4),
        "crossing_error_mm_max": round(float(cross_all.max()), 4),
        "textures_sink_s": round(textures_s, 2),
    }))


if __name__ == "__main__":
    main()
