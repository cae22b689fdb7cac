"""The command line: run/plan pipelines, list node types, manage the cache.

Every operator error ends as one line on stderr and a non-zero exit (2 for problems the operator
can fix, 1 for unexpected failures, whose traceback goes to a log file). Imports are lazy so that a
fully cached run stays fast: nothing heavy is imported before it is needed.

The application's entry point calls :func:`main` with its :class:`.app.App`; the app's own
commands live in the modules it lists in ``App.cli_extensions``, each exposing ``register(app)``
that adds its commands to the typer app.
"""
from __future__ import annotations

import importlib
import importlib.util
import os
import sys
from typing import Any, Optional

import typer

try:  # typer >= 0.20 vendors click as typer._click; older versions use click itself
    from typer import _click as click
except ImportError:  # pragma: no cover - depends on the installed typer
    import click  # type: ignore[no-redef]

from . import interrupts
from .app import App, configure, current
from .errors import NodeFailed, UserError

CORE_COMMANDS = ("run", "plan", "nodes", "cache")

SetOption = typer.Option(None, "-S", "--set", metavar="PATH=VALUE",
                         help="Override a value of the pipeline (VALUE is YAML), e.g. -S params.diagonal_mm=200 "
                              "(short: -S diagonal_mm=200) or -S nodes.remesh.params.target_edge_mm=2 "
                              "(short: -S remesh.target_edge_mm=2).")
CacheDirOption = typer.Option(None, "--cache-dir", help="Cache folder (default: $<APP>_CACHE_DIR or ./cache).")


def _store(cache_dir: Optional[str]):
    from .store import Store, default_cache_dir

    return Store(cache_dir or default_cache_dir())


def run(
    pipeline: str = typer.Argument(..., help="Pipeline YAML file."),
    overrides: Optional[list[str]] = SetOption,
    out: Optional[str] = typer.Option(None, "--out", help="Output folder (default: out/<pipeline name>)."),
    scheduler: str = typer.Option("auto", "--scheduler",
                                  help="auto | sync | threads | processes | local-cluster | tcp://HOST:PORT (a dask.distributed "
                                       "scheduler)."),
    explain: bool = typer.Option(False, "--explain", help="Say why each node that runs is not a cache hit."),
    cache_dir: Optional[str] = CacheDirOption,
) -> None:
    """Run a pipeline: cached nodes are reused, the rest run on the scheduler; sinks write into --out."""
    from .runner import run_pipeline

    result = run_pipeline(pipeline, overrides, out_dir=out, scheduler=scheduler, cache_dir=cache_dir,
                          explain=explain, on_plan=_print_explain if explain else None, progress=_progress)
    for problem in result.repaired:
        print(f"{current().name}: note: damaged cache entry deleted and recomputed: {problem}", file=sys.stderr)
    _print_table(result.plan, result.status)
    ran = len(result.ran())
    print(f"{ran} ran, {len(result.plan.instances) - ran} cached, {result.seconds:.2f} s; outputs in {result.out_dir}")


def plan_command(
    pipeline: str = typer.Argument(..., help="Pipeline YAML file."),
    overrides: Optional[list[str]] = SetOption,
    cache_dir: Optional[str] = CacheDirOption,
) -> None:
    """Show what a run would do: every node instance, its cache key, hit or miss, and why it would run."""
    from . import plan as planning
    from .runner import make_plan

    plan = make_plan(pipeline, overrides, cache_dir)
    planning.explain(plan)
    from rich.console import Console
    from rich.table import Table

    table = Table("node", "branch", "type", "key", "status", "why")
    for inst in plan.instances:
        table.add_row(inst.node, inst.label, inst.type_name, inst.key[:12],
                      "run" if inst.runs else ("cached" if inst.cached else "skip"), inst.reason)
    Console().print(table)
    print(f"{len(plan.to_run)} of {len(plan.instances)} node instances would run")


def nodes(name: Optional[str] = typer.Argument(None, help="Only node types containing this text.")) -> None:
    """List the node types with their inputs, outputs, params (type, default, description) and docs."""
    from pydantic_core import PydanticUndefined

    from . import registry

    specs = registry.load()
    for type_name in sorted(specs):
        if name and name not in type_name:
            continue
        spec = specs[type_name]
        print(f"{type_name}{'  (sink)' if spec.sink else ''}")
        if spec.doc:
            print("  " + spec.doc.split("\n\n")[0].replace("\n", "\n  "))
        print(f"  inputs: {', '.join(spec.inputs) or '-'}    outputs: {', '.join(spec.outputs)}")
        for field, info in spec.params.model_fields.items():
            annotation = info.annotation.__name__ if isinstance(info.annotation, type) else \
                str(info.annotation).replace("typing.", "")
            default = "required" if info.default is PydanticUndefined and info.default_factory is None else \
                f"default {info.get_default(call_default_factory=True)!r}"
            print(f"    {field}: {annotation} ({default}){' - ' + info.description if info.description else ''}")
        print()


cache_app = typer.Typer(help="Inspect and clean the cache.", no_args_is_help=True, add_completion=False)


@cache_app.command("info")
def cache_info(cache_dir: Optional[str] = CacheDirOption) -> None:
    """Where the cache is, how many entries, how big."""
    from . import maintenance

    for line in maintenance.info(_store(cache_dir)):
        print(line)


@cache_app.command("gc")
def cache_gc(
    pipelines: Optional[list[str]] = typer.Argument(None, help="Keep every entry these pipelines use."),
    older_than: Optional[float] = typer.Option(None, "--older-than", metavar="DAYS",
                                               help="Only drop entries not used for this many days."),
    overrides: Optional[list[str]] = SetOption,
    cache_dir: Optional[str] = CacheDirOption,
) -> None:
    """Drop stale temp dirs and corrupt entries; with PIPELINES, drop entries they do not use; with
    --older-than, drop entries unused for DAYS days (both given: unused by them AND old)."""
    from . import maintenance
    from .runner import make_plan

    store = _store(cache_dir)
    keep = None
    if pipelines:
        keep = set()
        for p in pipelines:
            keep |= {inst.key for inst in make_plan(p, overrides, store.root).instances}
    for line in maintenance.gc(store, keep, older_than):
        print(line)


@cache_app.command("clear")
def cache_clear(cache_dir: Optional[str] = CacheDirOption) -> None:
    """Delete every entry, lock, run record, log and temp dir in the cache."""
    from . import maintenance

    print(maintenance.clear(_store(cache_dir)))


class _Running:
    """Progress events from the runner: which instances run, since when."""

    def __init__(self, on_change: Any = None):
        self.started: dict[str, float] = {}
        self.finished = 0
        self.on_change = on_change

    def start(self, label: str) -> None:
        import time

        self.started[label] = time.monotonic()

    def done(self, label: str) -> None:
        self.started.pop(label, None)
        self.finished += 1
        if self.on_change:
            self.on_change()

    def describe(self, width: int) -> str:
        """``running: a 12s, b[x=1] 3s`` cut to ``width`` characters."""
        import time

        now = time.monotonic()
        parts = [f"{label} {now - t:.0f}s" for label, t in sorted(self.started.items(), key=lambda kv: kv[1])]
        text = "running: " + ", ".join(parts) if parts else "starting"
        return text if len(text) <= width else text[: max(0, width - 1)] + "…"


def _progress(total: int):
    """Context manager yielding a :class:`_Running`; on a terminal, a live display on stderr of the
    bar, the count, the elapsed time and the running nodes with their own elapsed time."""
    import contextlib

    @contextlib.contextmanager
    def manager():
        if total == 0 or not sys.stderr.isatty():
            yield _Running()
            return
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, ProgressColumn, TimeElapsedColumn
        from rich.text import Text

        console = Console(stderr=True)
        events = _Running()

        class RunningColumn(ProgressColumn):
            def render(self, task: Any) -> Text:
                return Text(events.describe(max(20, console.width - 45)))

        with Progress(BarColumn(bar_width=20), MofNCompleteColumn(), TimeElapsedColumn(), RunningColumn(),
                      console=console, transient=True, refresh_per_second=4) as progress:
            task = progress.add_task("run", total=total)
            events.on_change = lambda: progress.update(task, completed=events.finished)
            yield events

    return manager()


def _print_explain(plan) -> None:
    if not plan.to_run:
        print(f"nothing to run: all {len(plan.instances)} node instances are cached")
    for inst in plan.to_run:
        print(f"{inst.id}: runs because {inst.reason}")


def _print_table(plan, status: dict[int, dict[str, Any]]) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table("node", "branch", "cached/ran", "seconds")
    for inst in plan.instances:
        s = status.get(id(inst))
        if s is None:
            table.add_row(inst.node, inst.label, "cached" if inst.cached else "skipped", "")
        else:
            table.add_row(inst.node, inst.label, s["status"], f"{s['seconds']:.2f}")
    Console(width=max(100, Console().width)).print(table)


def build_app(with_extensions: bool = True) -> typer.Typer:
    app = typer.Typer(help=f"{current().name}: {current().description}",
                      no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False,
                      rich_markup_mode=None)
    app.command("run")(run)
    app.command("plan")(plan_command)
    app.command("nodes")(nodes)
    app.add_typer(cache_app, name="cache")
    if with_extensions:
        for module in current().cli_extensions:
            try:
                found = importlib.util.find_spec(module) is not None
            except (ImportError, ValueError):
                found = False
            if found:  # an extension that is not installed (yet) is skipped
                importlib.import_module(module).register(app)
    return app


def main(application: App, argv: list[str] | None = None) -> None:
    """Run the command line of ``application``, turning every error into one line and an exit code.

    ``argv`` None means this process's own command line: then SIGINT/SIGTERM stay ignored once the
    command is done (the process is exiting); otherwise the previous handlers are put back.
    """
    previous = interrupts.install()
    try:
        _main(application, argv)
    finally:
        if argv is None:
            interrupts.ignore()
        else:
            interrupts.restore(previous)


def _main(application: App, argv: list[str] | None) -> None:
    configure(application)
    args = list(sys.argv[1:] if argv is None else argv)
    try:
        app = build_app(with_extensions=not args or args[0] not in CORE_COMMANDS)
        command = typer.main.get_command(app)
        result = command.main(args=args, prog_name=application.name, standalone_mode=False)
    except interrupts.Interrupted as exc:
        _fail("interrupted", exc.exit_code)
    except UserError as exc:
        _fail(str(exc), 2)
    except NodeFailed as exc:
        _fail(str(exc), 1)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except click.ClickException as exc:
        if type(exc).__name__ == "NoArgsIsHelpError":  # bare `APP` or `APP cache`: show help
            print(exc.format_message())
            sys.exit(0)
        _fail(exc.format_message() + f"  (see {application.name} --help)", 2)
    except (typer.Abort, KeyboardInterrupt):
        _fail("interrupted", 130)
    except Exception as exc:  # an engine bug: keep the traceback, show one line
        _fail(f"unexpected {type(exc).__name__}: {exc} (traceback: {_crash_log()})", 1)
    sys.exit(result if isinstance(result, int) else 0)


def _fail(message: str, code: int) -> None:
    interrupts.ignore()  # the one line below is the last word, even if Ctrl-C comes again
    first = " ".join(str(message).split("\n"))
    print(f"{current().name}: error: {first}", file=sys.stderr)
    sys.exit(code)


def _crash_log() -> str:
    import tempfile
    import traceback

    fd, path = tempfile.mkstemp(prefix=f"{current().name}-crash-", suffix=".log")
    with os.fdopen(fd, "w") as f:
        traceback.print_exc(file=f)
    return path

