"""``retrotouch project`` end to end on a synthetic sequence, and its one-line operator errors."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from proj_fixtures import BOARD, BoardCaptureSimulator, board_poses, bunny_layout, bunny_mm, demo_rig, write_depth_png
from retrotouch.nodes.data.scene import build_scene, save_scene
from retrotouch.nodes.projection.calibration import load_calibration, save_calibration
from retrotouch.nodes.projection.depth_frames import SyntheticDepthSource, demo_trajectory
from retrotouch.nodes.projection.structured_light import gray_code_patterns


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    root = tmp_path_factory.mktemp("proj_cli")
    mesh = bunny_mm(3000)
    (root / "run" / "projection").mkdir(parents=True)
    (root / "run" / "projection" / "bunny_scene.npz").write_bytes(save_scene(build_scene(mesh, bunny_layout(mesh, 8, 6))))
    save_calibration(demo_rig(320, 180), root / "rig.json")
    return root


def test_synthetic_sequence_writes_projector_frames(cli, run_folder):
    out = run_folder / "out"
    result = cli("project", "--layout", run_folder / "run", "--calibration", run_folder / "rig.json",
                 "--synthetic", "3", "--out", out, "--video")
    assert result.returncode == 0, result.stderr
    for layer in ("tx", "rx"):
        frames = sorted((out / layer).glob("frame_*.png"))
        assert [f.name for f in frames] == ["frame_000000.png", "frame_000001.png", "frame_000002.png"]
        img = cv2.imread(str(frames[-1]))
        assert img.shape == (180, 320, 3) and img.max() > 0
        assert (out / f"{layer}.mp4").stat().st_size > 0
    track = json.loads((out / "track.json").read_text())
    assert [r["status"] for r in track["records"]] == ["found", "tracked", "tracked"]
    assert all(r["error_deg"] < 1.0 and r["error_mm"] < 1.0 for r in track["records"])


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--synthetic", "2", "--frames", "."], "exactly one of --frames"),
        (["--frames", "nowhere"], "is not a folder"),
        (["--synthetic", "1", "--mode", "texture"], "needs a scene with baked textures"),
    ],
)
def test_operator_errors_are_one_line(cli, run_folder, extra, message):
    result = cli("project", "--layout", run_folder / "run", "--calibration", run_folder / "rig.json",
                 "--out", run_folder / "bad", *extra)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0]


def test_missing_scene_and_calibration(cli, run_folder, tmp_path):
    result = cli("project", "--layout", tmp_path, "--calibration", run_folder / "rig.json", "--synthetic", "1", "--out", tmp_path / "o")
    assert result.returncode == 2 and "no projection/*_scene.npz" in result.stderr
    result = cli("project", "--layout", run_folder / "run", "--calibration", tmp_path / "none.json", "--synthetic", "1", "--out", tmp_path / "o")
    assert result.returncode == 2 and "cannot read calibration file" in result.stderr


def test_recorded_depth_folder(cli, run_folder):
    """--frames plays 16-bit depth PNGs registered to the calibrated camera."""
    mesh = bunny_mm(3000)
    depth_dir = run_folder / "depth"
    depth_dir.mkdir()
    for frame in SyntheticDepthSource(mesh, demo_rig(320, 180).camera, demo_trajectory(2, seed=5)).frames():
        write_depth_png(depth_dir / f"{frame.index:05d}.png", frame.depth_mm)
    out = run_folder / "out_frames"
    result = cli("project", "--layout", run_folder / "run" / "projection" / "bunny_scene.npz",
                 "--calibration", run_folder / "rig.json", "--frames", depth_dir, "--out", out)
    assert result.returncode == 0, result.stderr
    track = json.loads((out / "track.json").read_text())
    assert [r["status"] for r in track["records"]] == ["found", "tracked"]
    assert "error_deg" not in track["records"][0]  # no truth for recorded frames
    assert len(list((out / "rx").glob("frame_*.png"))) == 2


def test_patterns_and_calibration_commands(cli, tmp_path):
    """project-patterns writes what the projector shows; project-calibrate turns saved captures into a calibration."""
    rig = demo_rig(640, 360)
    result = cli("project-patterns", "--projector-size", "640x360", "--out", tmp_path / "patterns", "--board", "9x7")
    assert result.returncode == 0, result.stderr
    shown = sorted((tmp_path / "patterns").glob("[0-9][0-9].png"))
    assert len(shown) == len(gray_code_patterns(640, 360)) == 2 + 2 * (10 + 9)
    assert cv2.imread(str(tmp_path / "patterns" / "board.png")) is not None
    sim = BoardCaptureSimulator(rig, BOARD)
    for k, T in enumerate(board_poses(6)):
        cap = sim.capture(T, seed=k)
        pose_dir = tmp_path / "captures" / f"pose{k}"
        pose_dir.mkdir(parents=True)
        for i, img in enumerate([cap.white, cap.black, *cap.stack]):
            cv2.imwrite(str(pose_dir / f"{i:02d}.png"), np.clip(np.rint(img), 0, 255).astype(np.uint8))
    result = cli("project-calibrate", "--captures", tmp_path / "captures", "--projector-size", "640x360",
                 "--board", f"{BOARD.cols}x{BOARD.rows}", "--square-mm", str(BOARD.square_mm), "--out", tmp_path / "rig.json")
    assert result.returncode == 0, result.stderr
    cal = load_calibration(tmp_path / "rig.json")
    assert max(cal.rms_camera_px, cal.rms_projector_px, cal.rms_stereo_px) < 0.3
    assert np.linalg.norm(cal.T - rig.T) < 1.5
    (tmp_path / "captures" / "pose0" / "05.png").unlink()
    result = cli("project-calibrate", "--captures", tmp_path / "captures", "--projector-size", "640x360",
                 "--square-mm", "15", "--out", tmp_path / "x.json")
    assert result.returncode == 2 and "05.png is missing" in result.stderr
