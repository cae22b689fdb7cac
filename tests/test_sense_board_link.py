"""The board as it really talks: the binary format's self-alignment (dropped bytes, garbage), the
handshake variant and the binary stream through the real termios path of a pty, and `sense --probe`."""
from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from retrotouch.nodes.data.sensing_map import load_sensing_map
from retrotouch.nodes.sensing.binary_frames import BinaryFrameParser
from retrotouch.nodes.sensing.frames import encode_binary_frame
from retrotouch.nodes.sensing.pty_board import PtyBoard, frames_through_pty
from retrotouch.nodes.sensing.scripts import ScriptBuilder
from retrotouch.nodes.sensing.synthetic_map import synthetic_bunny_map
from retrotouch.nodes.sensing.virtual_board import BoardParams, VirtualBoard
from sense_helpers import parse_stream


def noisy_frames(seed: int, count: int, sigma: float = 3.0) -> list[np.ndarray]:
    """Frames of a quiet board: fixed baselines 9650-10360 counts (as measured on an FT5x06) plus noise."""
    rng = np.random.default_rng(seed)
    baseline = rng.uniform(9650, 10360, (21, 12))
    return [np.rint(baseline + rng.normal(0, sigma, (21, 12))).astype(np.int64) for _ in range(count)]


def decoded(grid: np.ndarray) -> np.ndarray:
    """What the binary format carries of ``grid`` (value - min wraps above 255)."""
    base = grid.min()
    return base + ((grid - base) & 0xFF)


def damaged_stream(seed: int, sigma: float, damage: list[tuple[bool, int, bytes]], cuts: list[int]):
    """60 frames; frames 5, 15, 25, 35 lose a byte (at a position) or get status text and garbage in
    front; the last 15 frames let a search finish. Returns the chunks, the frames as the format
    carries them and the number of incidents."""
    frames = noisy_frames(seed, 60, sigma)
    data = bytearray()
    for k, grid in enumerate(frames):
        encoded = encode_binary_frame(grid)
        if k in (5, 15, 25, 35):
            drop, position, garbage = damage[k // 10]
            position %= len(encoded)
            encoded = encoded[:position] + encoded[position + 1:] if drop else b"i2c write failed" + garbage + encoded
        data += encoded
    cuts = sorted(c % len(data) for c in cuts)
    chunks = [bytes(data[a:b]) for a, b in zip([0, *cuts], [*cuts, len(data)])]
    return chunks, [decoded(grid) for grid in frames], 4


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10_000), st.sampled_from([1.0, 3.0, 8.0]),
       st.lists(st.tuples(st.booleans(), st.integers(0, 253), st.binary(max_size=40)), min_size=4, max_size=4),
       st.lists(st.integers(0, 20_000), max_size=12))
# a frame cut from the tail of the frame before the garbage and the garbage passed every check
@example(97, 8.0, [(False, 0, b"")] * 4, [])
# on a quiet board an offset a byte off looks as steady as the boundary
@example(2676, 1.0, [(True, 93, b""), (True, 8, b""), (False, 41, b"I\xbc\xf5m\xbf_R\xf4\x1f\x88\xdff\xb4\xfd02"),
                     (True, 55, b"")], [510, 4199, 14031, 18432, 19662, 13424, 2937, 6724, 4827, 2186, 8920])
def test_binary_alignment_survives_dropped_bytes_and_garbage(seed, sigma, damage, cuts):
    """Never a wrong frame (each one is the board's, in order); at most 2 frames lost per incident."""
    chunks, truth, incidents = damaged_stream(seed, sigma, damage, cuts)
    parser = BinaryFrameParser()
    out = parse_stream(chunks, parser) + parser.flush()
    positions = [next((k for k, t in enumerate(truth) if np.array_equal(frame, t)), None) for frame in out]
    assert None not in positions and positions == sorted(set(positions))
    assert len(out) >= len(truth) - 2 * incidents
    assert parser.stats.resyncs <= incidents


def test_binary_parser_finds_the_boundary_in_a_stream_joined_mid_frame():
    frames = noisy_frames(3, 12)
    data = b"".join(encode_binary_frame(g) for g in frames)[101:]  # the host connected mid-frame
    parser = BinaryFrameParser()
    out = parse_stream([data], parser) + parser.flush()
    assert len(out) == 11 and all(np.array_equal(a, decoded(b)) for a, b in zip(out, frames[1:]))
    assert parser.stats.dropped_bytes == 254 - 101


@pytest.fixture(scope="module")
def bunny(tmp_path_factory):
    return load_sensing_map(synthetic_bunny_map(tmp_path_factory.mktemp("bunny")))


@pytest.mark.parametrize("frame_format", ["ascii", "binary", "handshake"])
def test_every_format_through_the_pty_gives_the_boards_frames(bunny, frame_format):
    """The board speaks the format on a pty; the reader (pyserial on the pty's termios) gets every frame."""
    params = BoardParams(seed=4, baseline_low=9980, baseline_high=10100)
    twin = VirtualBoard(bunny, params)
    expected = [twin.frame(k / params.rate_hz) for k in range(50)]
    got = [frame.values for frame in frames_through_pty(VirtualBoard(bunny, params), None, fast=True,
                                                        frame_format=frame_format, frames=50)]
    if frame_format == "binary":
        expected = [decoded(grid) for grid in expected]
    assert len(got) == 50 and all(np.array_equal(a, b) for a, b in zip(got, expected))


def test_handshake_board_waits_for_the_host_and_repeats_its_sync_line(bunny):
    import os
    import select
    import time

    with PtyBoard(VirtualBoard(bunny, BoardParams()), None, frame_format="handshake", frames=3) as board:
        slave = os.open(board.port, os.O_RDWR | os.O_NOCTTY)
        try:
            received = b""
            deadline = time.monotonic() + 1.3
            while time.monotonic() < deadline:
                if select.select([slave], [], [], 0.05)[0]:
                    received += os.read(slave, 4096)
            assert received.count(b"RX:12:TX:21:SYNC\r\n") in (3, 4)  # every 0.5 s, no frame yet
            os.write(slave, b"s")  # the answer
            time.sleep(0.3)
            assert not select.select([slave], [], [], 0.0)[0]  # no frame until it is requested
            os.write(slave, b"sss")  # requests waiting together give one frame
            time.sleep(0.3)
            lines = os.read(slave, 65536).split(b"\r\n")
            assert len(lines) == 2 and lines[0].count(b",") == 251
        finally:
            os.close(slave)


def test_binary_stream_with_dropped_bytes_through_the_pty_keeps_touches(bunny):
    """A press on a board whose link drops a byte every 13th frame (a search needs 10 clean frames):
    still found, no ghost touch."""
    from retrotouch.nodes.sensing.processing import TouchProcessor

    params = BoardParams(seed=9, baseline_low=9980, baseline_high=10020, signal_counts=150, drift_fraction=0.0)
    script = ScriptBuilder(bunny, params, seed=9).build([{"gesture": "press", "at": {"cell": 10}, "ms": 1500}])
    processor = TouchProcessor(bunny)
    statuses, downs, frames = [], 0, 0
    for frame in frames_through_pty(VirtualBoard(bunny, params), script, fast=True, frame_format="binary",
                                    drop_byte_every=13, on_status=statuses.append):
        result = processor.process(frame.values, frame.t)
        downs += sum(event["type"] == "touch_down" for event in result.events)
        frames += 1
    total = int(np.ceil(script.duration * params.rate_hz))
    assert total - 2 * (total // 13) <= frames < total
    assert downs == 1
    assert statuses and all("resynced" in line and "\n" not in line for line in statuses)


@pytest.mark.parametrize("frame_format", ["ascii", "binary", "handshake"])
def test_probe_names_the_format_rate_and_channels_of_a_board(bunny, frame_format):
    from retrotouch.nodes.sensing.probe import probe_port

    params = BoardParams(seed=5, rate_hz=40.0, baseline_low=9980, baseline_high=10100)
    with PtyBoard(VirtualBoard(bunny, params), None, frame_format=frame_format, frames=200) as board:
        report = probe_port(board.port, seconds=1.5)
    assert report["format"] == frame_format and (report["rx"], report["tx"]) == (12, 21)
    assert 0.8 * 40 <= report["frames_per_s"] <= 1.2 * 40
    assert f"--format {frame_format}" in report["command"]


def _serve_on_pty(data: bytes, repeat_s: float = 0.05, seconds: float = 1.0):
    """A pty that gets ``data`` every ``repeat_s`` for ``seconds`` (a board that is no Muca raw sketch)."""
    import os
    import pty
    import threading
    import time

    master, slave = pty.openpty()
    import tty

    tty.setraw(slave)

    def write() -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            if data:
                os.write(master, data)
            time.sleep(repeat_s)

    thread = threading.Thread(target=write, daemon=True)
    thread.start()
    return os.ttyname(slave), thread, (master, slave)


@pytest.mark.parametrize(("data", "expected", "advice"), [
    (b"0:0:120:340:55|1:2:400:80:61|\r\n", "touch-point", "raw sketch"),
    (b"", "unknown", "nothing received"),
    (bytes(range(7, 250, 3)) * 3, "unknown", "--baud"),
])
def test_probe_tells_touch_point_mode_silence_and_noise_apart(data, expected, advice):
    import os

    from retrotouch.nodes.sensing.probe import probe_port

    port, thread, fds = _serve_on_pty(data)
    try:
        report = probe_port(port, seconds=0.6)
    finally:
        thread.join()
        for fd in fds:
            os.close(fd)
    assert report["format"] == expected and advice in report["command"]


def test_sense_probe_prints_one_line_or_one_json_object(bunny, tmp_path):
    import typer
    from typer.testing import CliRunner

    from retrotouch.nodes.sensing.cli import register

    app = typer.Typer()
    register(app)
    app.command("other")(lambda: None)
    params = BoardParams(seed=5, rate_hz=40.0, baseline_low=9980, baseline_high=10100)
    with PtyBoard(VirtualBoard(bunny, params), None, frame_format="binary", frames=400) as board:
        line = CliRunner().invoke(app, ["sense", "--probe", board.port, "--probe-seconds", "1"]).stdout
        data = CliRunner().invoke(app, ["sense", "--probe", board.port, "--probe-seconds", "1", "--json"]).stdout
    assert len(line.strip().splitlines()) == 1 and "binary frames" in line and "12 RX x 21 TX" in line
    report = json.loads(data)
    assert report["format"] == "binary" and report["frames"] >= 20
    missing = CliRunner().invoke(app, ["sense", "--probe", str(tmp_path / "nope")])
    assert missing.exit_code != 0 and "cannot open serial port" in str(missing.exception)


def test_a_binary_recording_replays_every_frame(bunny, tmp_path):
    from retrotouch.nodes.sensing.recording import replay_frames

    params = BoardParams(seed=6, baseline_low=9980, baseline_high=10100)
    path = tmp_path / "binary.jsonl"
    live = [f.values for f in frames_through_pty(VirtualBoard(bunny, params), None, fast=True, frame_format="binary",
                                                 frames=30, record=path)]
    replayed = [f.values for f in replay_frames(path)]
    assert len(live) == len(replayed) == 30 and all(np.array_equal(a, b) for a, b in zip(live, replayed))
