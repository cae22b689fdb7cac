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
from retrotouch.nodes.sensing.processing import ProcessingParams, TouchProcessor
from retrotouch.nodes.sensing.scripts import ScriptBuilder
from retrotouch.nodes.sensing.synthetic_map import synthetic_bunny_map
from retrotouch.nodes.sensing.virtual_board import BoardParams, VirtualBoard

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
