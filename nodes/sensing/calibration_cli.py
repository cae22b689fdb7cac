"""``retrotouch sense --calibrate``: the guided calibration session on a board, a recording or the
virtual board (a simulated operator follows the prompts), written to a calibration file."""
from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .sinks import EventSinks, status_event


def run_calibration(layout_path: Path, source: Any, out: Path, open_frames: Callable, live_view: Callable | None) -> None:
    """Prompt (stderr, ``calibration`` status events on stdout and, with ``live_view`` (processor ->
    LiveView), on the live page), collect, estimate, write ``out``."""
    from ..data.sensing_map import load_sensing_map
    from .calibration import calibrate
    from .evaluation import calibrate_simulator
    from .processing import TouchProcessor

    sensing_map = load_sensing_map(layout_path)
    sinks = EventSinks()
    processor = TouchProcessor(sensing_map)
    live = None if live_view is None else live_view(processor)

    def prompt(text: str) -> None:
        print(text, file=sys.stderr, flush=True)
        sinks.emit(status_event("calibration", text))
        if live is not None:
            live.prompt = text

    session_options = {"processor": processor, "on_result": None if live is None else live.publish}
    frames = reader = None
    try:
        if source.steps is not None:  # --simulate: the operator is simulated too
            calibration, session = calibrate_simulator(sensing_map, source.board_params, seed=source.board_params.seed,
                                                       prompt=prompt, **session_options)
        else:
            frames, reader = open_frames(source, sensing_map, sinks)
            calibration, session = calibrate(frames, sensing_map, prompt=prompt, **session_options)
    finally:
        if hasattr(frames, "close"):
            frames.close()
        if reader is not None:
            reader.close()
        if live is not None:
            live.stop()
    calibration.save(out)
    summary = calibration.summary()
    line = (f"calibration written to {out}: {session['accepted']} of {session['targets']} touches "
            f"({summary['crossings_measured']} crossings), no-pad gain {summary['no_pad_gain']:.2f}, coupling width "
            f"{summary['coupling_sigma_mm']:.2f} mm"
            + ("" if summary["coupling_tail"] is None else f" tail {summary['coupling_tail']:.2f}")
            + f" (finger radius {summary['finger_radius_mm']:.2f} mm)"
            + ("" if summary["crossings_moved_mm_median"] is None else
               f", crossings {summary['crossings_moved_mm_median']:.1f} mm from the map (median; max "
               f"{summary['crossings_moved_mm_max']:.1f} mm), placed to {summary['position_std_mm_median']:.2f} mm "
               f"(median spread; max {summary['position_std_mm_max']:.2f} mm, {len(session['refined'])} of the least "
               "certain touched again)"))
    print(line, file=sys.stderr, flush=True)
    sinks.emit(status_event("calibration", line))
