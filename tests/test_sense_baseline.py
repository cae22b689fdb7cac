"""The processing side of issue 14: common modes of Tx rows and Rx columns removed from the deltas
and left out of the noise the thresholds use; per-crossing gains and the no-pad gain learned from
ordinary touches; and the processing never reads the simulator's board settings."""
from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from retrotouch.nodes.data.sensing_map import load_sensing_map
from retrotouch.nodes.sensing.baseline import Baseline
from retrotouch.nodes.sensing.evaluation import EvalParams, evaluate_simulator
from retrotouch.nodes.sensing.processing import ProcessingParams, TouchProcessor
from retrotouch.nodes.sensing.scripts import ScriptBuilder
from retrotouch.nodes.sensing.synthetic_map import synthetic_bunny_map
from retrotouch.nodes.sensing.virtual_board import REALISTIC_BOARD, BoardParams, VirtualBoard

SENSING = Path(__file__).resolve().parents[1] / "nodes" / "sensing"
# The board side: the simulator, its scripts and pty, the evaluation that drives both, and the CLI.
BOARD_SIDE = {"virtual_board.py", "scripts.py", "pty_board.py", "evaluation.py", "locations.py", "cli.py",
              "calibration_cli.py", "live_view.py", "synthetic_map.py"}


@pytest.fixture(scope="module")
def bunny(tmp_path_factory):
    path = synthetic_bunny_map(tmp_path_factory.mktemp("bunny"), cells=120)
    return path, load_sensing_map(path)


def test_row_and_column_noise_is_removed_and_not_counted_as_noise():
    rng = np.random.default_rng(0)
    shape = (21, 12)
    base = rng.uniform(9650, 10360, shape)

    def frame(touch: np.ndarray | None = None) -> np.ndarray:
        rows, columns = rng.normal(0, 4.0, (21, 1)), rng.normal(0, 4.0, (1, 12))
        raw = base + rng.normal(0, 1.0, shape) + rows + columns
        return (raw if touch is None else raw + touch).ravel()

    baseline = Baseline(shape, ProcessingParams())
    for _ in range(20):
        baseline.calibrate(frame())
    # Without the row/column step the sigma would be sqrt(1 + 16 + 16) = 5.7 counts.
    assert np.median(baseline.sigma()) < 1.4
    touch = np.zeros(shape)
    touch[5, 3:6] = [80.0, 200.0, 80.0]  # one touch on three channels of a row
    touch[6:8, 4] = 60.0
    touched = np.zeros(21 * 12, dtype=bool)
    residuals, touch_errors = [], []
    for _ in range(200):
        delta = baseline.delta(frame(touch), np.ones(21 * 12, dtype=bool), baseline.sigma(), touched)
        quiet = touch.ravel() == 0
        residuals.append(delta[quiet])
        touch_errors.append(delta[~quiet] - touch.ravel()[~quiet])
    assert np.std(residuals) < 1.3
    # Without the removal the touched channels would be off by sqrt(32) = 5.7 counts (sigma).
    assert np.abs(np.mean(touch_errors, axis=0)).max() < 1.0 and np.std(touch_errors) < 2.0


def test_line_drift_is_removed_where_a_touch_holds_a_whole_line_and_where_channels_leave_the_quiet_band():
    """Slow drift of every Tx and Rx line (15 counts, periods 60-240 s) over white noise of 0.75
    counts, a quiet board's: a touch holds Tx line 3 and its channels for 3 s of every 10, and two
    channels carry a static offset of 12 counts (out of the quiet band: they never update). At rest,
    no channel may read above the on threshold, and the offset channels read their offset: a
    baseline that followed the raw counts carried the line drift, and a channel out of the quiet band
    drifted on with its lines (-> false touches at rest on a quiet board)."""
    rng = np.random.default_rng(3)
    shape, params = (21, 12), ProcessingParams()
    base = rng.uniform(9650, 10360, shape)
    phase, period = rng.uniform(0, 2 * np.pi, 33), rng.uniform(60.0, 240.0, 33)
    offset = np.zeros(shape)
    offset[10, 6], offset[11, 1] = 12.0, 12.0
    touch = np.zeros(shape)
    touch[3] = 150.0

    def frame(t: float, touched: bool) -> np.ndarray:
        drift = 15.0 * np.sin(2 * np.pi * t / period + phase)
        raw = base + drift[:21, None] + drift[None, 21:] + rng.normal(0, 0.75, shape) + offset
        return (raw + touch if touched else raw).ravel()

    baseline = Baseline(shape, params)
    for k in range(params.calibration_frames):
        baseline.calibrate(frame(k / 10, False) - offset.ravel())
    valid, held = np.ones(21 * 12, dtype=bool), (touch > 0).ravel()
    at_rest, offset_reads = [], []
    for k in range(params.calibration_frames, 1800):
        t = k / 10
        touched = t % 10 < 3
        sigma = baseline.sigma()
        delta = baseline.delta(frame(t, touched), valid, sigma, held if touched else ~valid)
        baseline.update(delta, valid, sigma, held if touched else None, t, 0.1)
        if t % 10 > 3.5:
            plain = offset.ravel() == 0
            at_rest.append(np.max(delta[plain] / sigma[plain]))
            offset_reads.append(delta[~plain])
    assert max(at_rest) < params.on_sigma
    assert np.abs(np.mean(offset_reads, axis=0) - 12.0).max() < 1.5


def test_a_quieter_board_never_breaks_the_processing(bunny):
    """The simulator's default board (correlated noise, spikes, per-channel drift, a heavy-tailed
    finger) at SNR 300 instead of 60: every press one touch-down, no ghost, nothing at rest (before
    the line offsets were kept from frame to frame: ghosts and false touches at SNR 150-400)."""
    path, _ = bunny
    summary = evaluate_simulator(path, REALISTIC_BOARD.model_copy(update={"snr": 300.0}), EvalParams(seed=0),
                                 through_pty=False).summary()
    assert summary["missed_presses"] == 0 and summary["presses_without_one_touch_down"] == 0
    assert summary["ghost_touches"] == 0 and summary["false_touches_at_rest"] == 0
    assert summary["localization_error_mm_mean"] < 4.0


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            names.add((node.module or "").split(".")[-1])
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.Import):
            names.update(alias.name.split(".")[-1] for alias in node.names)
    return names


def test_the_processing_never_reads_the_board_settings():
    """No module of the processing chain imports the simulator or its settings, and the processor
    takes a sensing map, its own params and (optionally) measured gains: nothing of the board."""
    processing = sorted(p for p in SENSING.glob("*.py") if p.name not in BOARD_SIDE | {"__init__.py"})
    assert {p.name for p in processing} >= {"processing.py", "baseline.py", "coupling_fit.py", "gain_learning.py",
                                            "contacts.py", "plane_fit.py", "tracking.py", "calibration.py"}
    for path in processing:
        imported = _imports(path)
        assert not imported & {"virtual_board", "BoardParams", "REALISTIC_BOARD", "VirtualBoard", "scripts",
                               "pty_board", "evaluation"}, path.name
    import inspect

    assert list(inspect.signature(TouchProcessor).parameters) == ["sensing_map", "params", "cell_gain"]


def test_gains_and_the_no_pad_gain_are_learned_from_ordinary_touches(bunny):
    """A board with a 25 % per-cell gain spread and no-pad gain 0.3 (the processing assumes 1 and
    0.5): after 300 presses anywhere, the gains of the crossings touched often are closer to the
    board's than the assumed ones (measured: median log error 0.175 -> 0.144), and the no-pad gain
    is estimated within 25 %."""
    _, sensing_map = bunny
    params = BoardParams(cell_gain_jitter=0.25, no_pad_gain=0.3, seed=4)
    board = VirtualBoard(sensing_map, params)
    builder = ScriptBuilder(sensing_map, params, seed=4)
    script = builder.build([{"gesture": "press", "at": "random", "ms": 400, "gap_ms": 400} for _ in range(300)])
    processor = TouchProcessor(sensing_map)
    initial = processor.cell_gain.copy()
    for k in range(int(script.duration * params.rate_hz)):
        t = k / params.rate_hz
        processor.process(board.frame(t, script.fingers_at(t)), t)
    learned = processor.fit.gains.learned >= 3.0
    assert learned.sum() >= 0.5 * sensing_map.cell_count
    # The gains' scale is free (the touch amplitude carries it): compare after the padded median.
    truth = board.gain / np.median(board.gain[sensing_map.cell_pad & learned])
    error_before = np.abs(np.log(initial / truth))[learned]
    error_after = np.abs(np.log(processor.cell_gain / truth))[learned]
    assert np.median(error_after) < 0.9 * np.median(error_before)
    no_pad = ~sensing_map.cell_pad & ~learned
    if no_pad.any():
        assert np.median(processor.cell_gain[no_pad]) == pytest.approx(np.median(truth[~sensing_map.cell_pad]), rel=0.25)
