"""What the command line prints: the live progress display, tables, the JSON run summary.

Tables go to a terminal as rich tables whose cells wrap instead of being cut; piped (not a
terminal), they are plain columns separated by two spaces with every cell whole, one row a line,
so ``grep``/``awk`` see the full values.
"""
from __future__ import annotations

import contextlib
import os
import sys
import time
from typing import Any, Callable, Iterator, TextIO

SUMMARY_FORMAT_VERSION = 2


class RunningNodes:
    """Progress events from the runner: which instances run, since when."""

    def __init__(self) -> None:
        self.started: dict[str, float] = {}
        self.finished = 0
        self.on_done: Callable[[], None] | None = None

    def start(self, label: str) -> None:
        self.started[label] = time.monotonic()

    def done(self, label: str) -> None:
        self.started.pop(label, None)
        self.finished += 1
        if self.on_done:
            self.on_done()

    def describe(self, width: int) -> str:
        """``running: a 12s, b[x=1] 3s`` (longest running first), cut to ``width`` characters."""
        now = time.monotonic()
        parts = [f"{label} {now - t:.0f}s" for label, t in sorted(self.started.items(), key=lambda kv: kv[1])]
        text = "running: " + ", ".join(parts) if parts else "starting"
        return text if len(text) <= width else text[: max(0, width - 1)] + "…"


@contextlib.contextmanager
def progress(total: int) -> Iterator[RunningNodes]:
    """Yields the :class:`RunningNodes` the runner reports to; on a terminal, a live line on stderr
    with a bar, done/total, the elapsed time and the running nodes with their own elapsed time."""
    events = RunningNodes()
    if total == 0 or not sys.stderr.isatty():
        yield events
        return
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, ProgressColumn, TimeElapsedColumn
    from rich.text import Text

    console = Console(stderr=True)

    class RunningColumn(ProgressColumn):
        def render(self, task: Any) -> Text:
            return Text(events.describe(max(20, console.width - 45)))

    with Progress(BarColumn(bar_width=20), MofNCompleteColumn(), TimeElapsedColumn(), RunningColumn(),
                  console=console, transient=True, refresh_per_second=4) as bar:
        task = bar.add_task("run", total=total)
        events.on_done = lambda: bar.update(task, completed=events.finished)
        yield events


def print_table(headers: list[str], rows: list[list[str]], file: TextIO | None = None) -> None:
    """A table: rich with wrapping cells on a terminal, plain whole columns otherwise."""
    out = file or sys.stdout
    if out.isatty():
        from rich.console import Console
        from rich.table import Table

        table = Table()
        for header in headers:
            table.add_column(header, overflow="fold")
        for row in rows:
            table.add_row(*row)
        Console(file=out).print(table)
        return
    widths = [max([len(h)] + [len(r[i]) for r in rows]) for i, h in enumerate(headers)]
    for row in [headers, *rows]:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip(), file=out)


def instance_rows(plan: Any, status: dict[int, dict[str, Any]]) -> list[list[str]]:
    """``node, branch, cached/ran, seconds`` rows of the instances the run sent to a scheduler."""
    return [[i.node, i.label, status[id(i)]["status"], f"{status[id(i)]['seconds']:.2f}"]
            for i in plan.instances if id(i) in status]


def note_of(inst: Any, status: dict[int, dict[str, Any]]) -> str | None:
    """The one-line note (``note=`` of ``graph.node.node``) of an instance's output, ran or cached, or None."""
    if id(inst) in status:
        return status[id(inst)].get("note")
    return inst.cached.note if inst.cached is not None else None


def note_lines(plan: Any, status: dict[int, dict[str, Any]]) -> list[str]:
    """``id: note`` of every instance whose output carries a note, in plan order."""
    return [f"{inst.id}: {note}" for inst in plan.instances if (note := note_of(inst, status))]


def run_summary(app_name: str, result: Any) -> dict[str, Any]:
    """The machine-readable summary of a run (``run --json``)."""
    nodes = []
    for inst in result.plan.instances:
        s = result.status.get(id(inst), {})
        nodes.append({"id": inst.id, "node": inst.node, "branch": inst.label, "type": inst.type_name,
                      "key": inst.key, "status": s.get("status", "cached" if inst.cached else "skipped"),
                      "seconds": round(s.get("seconds", 0.0), 6), "note": note_of(inst, result.status)})
    ran = len(result.ran())
    return {"format": f"{app_name}.run-summary/{SUMMARY_FORMAT_VERSION}", "pipeline": os.path.abspath(result.plan.file),
            "out_dir": result.out_dir, "manifest": os.path.join(result.out_dir, "manifest.json"), "seconds": round(result.seconds, 6),
            "ran": ran, "cached": len(result.plan.instances) - ran, "fallback": result.fallback, "repaired": result.repaired,
            "nodes": nodes}
