"""nodes/data/events.schema.json: every line `sense` emits validates against it and carries the
stream's format version; events that break the format do not validate."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import typer
import yaml
from typer.testing import CliRunner

from retrotouch.nodes.sensing.cli import register
from retrotouch.nodes.sensing.sinks import EVENTS_FORMAT, EventSinks, status_event
from retrotouch.nodes.sensing.synthetic_map import synthetic_bunny_map
from retrotouch.nodes.sensing.virtual_board import BoardParams

jsonschema = pytest.importorskip("jsonschema")
SCHEMA_PATH = Path(__file__).resolve().parents[1] / "nodes" / "data" / "events.schema.json"
GESTURES = {"tap", "double_tap", "long_press", "swipe", "pinch", "spread"}


@pytest.fixture(scope="module")
def schema():
    schema = json.loads(SCHEMA_PATH.read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    return schema


@pytest.fixture(scope="module")
def demo_lines(tmp_path_factory):
    """`sense --simulate --fast` over the demo of every gesture (the processing's twin board, so
    every gesture is recognised), as stdout lines."""
    folder = tmp_path_factory.mktemp("events")
    layout = synthetic_bunny_map(folder / "bunny").parent
    twin = folder / "twin.yaml"
    twin.write_text(yaml.safe_dump(BoardParams().model_dump(mode="json")))
    app = typer.Typer()
    register(app)
    app.command("other")(lambda: None)
    result = CliRunner().invoke(app, ["sense", "--simulate", "--fast", "--layout", str(layout), "--board", str(twin)])
    assert result.exit_code == 0, result.output
    return result.stdout.splitlines()


def test_schema_names_the_format_every_event_carries(schema):
    assert schema["properties"]["format"]["const"] == EVENTS_FORMAT == "retrotouch.events/1"


def test_every_line_sense_emits_validates_and_carries_the_version(schema, demo_lines):
    validator = jsonschema.Draft202012Validator(schema)
    events = [json.loads(line) for line in demo_lines]
    for event in events:
        validator.validate(event)
    assert all(event["format"] == EVENTS_FORMAT for event in events)
    types = {event["type"] for event in events}
    assert GESTURES | {"touch_down", "touch_move", "touch_up", "status"} <= types
    assert [e["kind"] for e in events if e["type"] == "status"] == ["baseline"]


def test_board_status_events_validate(schema, capsys):
    sinks = EventSinks()
    sinks.emit(status_event("board", "board on /dev/ttyACM0 went away at 12:00:00 (read failed)"))
    sinks.emit(status_event("calibration", "touch crossing 3 of 12", t=4.25))
    for line in capsys.readouterr().out.splitlines():
        jsonschema.validate(json.loads(line), schema)


@pytest.mark.parametrize("change", [
    lambda e: e.pop("format"),
    lambda e: e.update(format="retrotouch.events/0"),
    lambda e: e.update(type="hover"),
    lambda e: e.pop("point"),
    lambda e: e.update(point=[1.0, 2.0]),
    lambda e: e.update(extra=1),
])
def test_events_that_break_the_format_do_not_validate(schema, demo_lines, change):
    event = next(json.loads(line) for line in demo_lines if json.loads(line)["type"] == "touch_down")
    change(event)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(event, schema)
