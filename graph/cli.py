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

CORE_COMMANDS = ("run", "plan", "dag", "watch", "nodes", "cache")

SetOption = typer.Option(None, "-S", "--set", metavar="PATH=VALUE",
                         help="Override a value of the pipeline (VALUE is YAML), e.g. -S params.diagonal_mm=200 "
                              "(short: -S diagonal_mm=200) or -S nodes.remesh.params.target_edge_mm=2 "
                              "(short: -S remesh.target_edge_mm=2).")
CacheDirOption = typer.Option(None, "--cache-dir", help="Cache folder (default: $<APP>_CACHE_DIR or ./cache).")


def _store(cache_dir: Optional[str]):
    from .store import default_cache_dir, open_store

    return open_store(cache_dir or default_cache_dir())


def run(
    pipeline: str = typer.Argument(..., help="Pipeline YAML file."),
    overrides: Optional[list[str]] = SetOption,
    out: Optional[str] = typer.Option(None, "--out", help="Output folder (default: out/<pipeline name>)."),
    scheduler: str = typer.Option("auto", "--scheduler",
                                  help="auto | sync | threads | processes | local-cluster | tcp://HOST:PORT (a dask.distributed "
                                       "scheduler)."),
    explain: bool = typer.Option(False, "--explain", help="Say why each node that runs is not a cache hit."),
    targets: Optional[list[str]] = typer.Option(None, "--target", "-t", metavar="NODE",
                                                help="Run only this node (every branch) and what it needs; repeatable. "
                                                     "Only the sinks among them write into --out."),
    as_json: bool = typer.Option(False, "--json", help="Print a machine-readable run summary (JSON) instead of the table."),
    cache_dir: Optional[str] = CacheDirOption,
) -> None:
    """Run a pipeline: cached nodes are reused, the rest run on the scheduler; sinks write into --out."""
    import json

    from . import display
    from .runner import run_pipeline

    result = run_pipeline(pipeline, overrides, out_dir=out, scheduler=scheduler, cache_dir=cache_dir, explain=explain,
                          on_plan=_print_explain if explain and not as_json else None, progress=display.progress,
                          targets=targets)
    for problem in result.repaired:
        print(f"{current().name}: note: damaged cache entry deleted and recomputed: {problem}", file=sys.stderr)
    if as_json:
        print(json.dumps(display.run_summary(current().name, result), indent=1))
        return
    ran = len(result.ran())
    if result.status:
        display.print_table(["node", "branch", "cached/ran", "seconds"],
                            display.instance_rows(result.plan, result.status))
    for line in display.note_lines(result.plan, result.status):
        print(line)
    if result.fallback:
        print(f"fallback: {result.fallback['summary']}")
    print(f"{ran} ran, {len(result.plan.instances) - ran} cached, {result.seconds:.2f} s; outputs in {result.out_dir}")


def plan_command(
    pipeline: str = typer.Argument(..., help="Pipeline YAML file."),
    overrides: Optional[list[str]] = SetOption,
    targets: Optional[list[str]] = typer.Option(None, "--target", "-t", metavar="NODE",
                                                help="Only this node and what it needs; repeatable."),
    cache_dir: Optional[str] = CacheDirOption,
) -> None:
    """Show what a run would do: every node instance, its cache key, hit or miss, and why it would run."""
    from . import display
    from . import plan as planning
    from .runner import make_plan

    plan = make_plan(pipeline, overrides, cache_dir, targets)
    planning.explain(plan)
    display.print_table(["node", "branch", "type", "key", "status", "why"],
                        [[i.node, i.label, i.type_name, i.key[:12], "run" if i.runs else ("cached" if i.cached else "skip"),
                          i.reason] for i in plan.instances])
    print(f"{len(plan.to_run)} of {len(plan.instances)} node instances would run")
    fallback = plan.pipeline.fallback
    if fallback and not targets:
        print(f"then, when {fallback.value_name} is {fallback.side} {fallback.threshold:g}, again with "
              f"{' '.join(fallback.overrides)}")


def dag(
    pipeline: str = typer.Argument(..., help="Pipeline YAML file."),
    overrides: Optional[list[str]] = SetOption,
    fmt: str = typer.Option("mermaid", "--format", "-f", help="mermaid | dot | svg (svg needs Graphviz's dot)."),
    status: bool = typer.Option(False, "--status", help="Plan too, and colour each node: cached or would run."),
    cache_dir: Optional[str] = CacheDirOption,
) -> None:
    """Print the pipeline graph: one box per node (branches counted), one edge per input."""
    from . import dag as graph
    from .pipeline import load_pipeline

    if fmt not in graph.FORMATS:
        raise UserError(f"--format {fmt!r}: expected one of {', '.join(graph.FORMATS)}")
    states: dict[str, str] = {}
    if status:
        from .runner import make_plan

        plan = make_plan(pipeline, overrides, cache_dir)
        for inst in plan.instances:
            states[inst.node] = "would run" if inst.runs or states.get(inst.node) == "would run" else "cached"
        pipe = plan.pipeline
    else:
        pipe = load_pipeline(pipeline, overrides or [])
    sys.stdout.write(graph.render(pipe, fmt, states))


def watch_command(
    pipeline: str = typer.Argument(..., help="Pipeline YAML file."),
    overrides: Optional[list[str]] = SetOption,
    out: Optional[str] = typer.Option(None, "--out", help="Output folder (default: out/<pipeline name>)."),
    port: int = typer.Option(8770, "--port", help="Port of the page on 127.0.0.1 (0: any free port)."),
    scheduler: str = typer.Option("auto", "--scheduler", help="As for run."),
    cache_dir: Optional[str] = CacheDirOption,
) -> None:
    """Rerun the pipeline on every save of its file and serve a page of the result (Ctrl-C stops)."""
    from .runner import check_scheduler, default_out_dir
    from .watch import watch

    check_scheduler(scheduler)
    watch(pipeline, overrides or [], out or default_out_dir(pipeline), port=port, scheduler=scheduler,
          cache_dir=cache_dir, say=lambda line: print(line, flush=True))


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


def _print_explain(plan) -> None:
    if not plan.to_run:
        print(f"nothing to run: all {len(plan.instances)} node instances are cached")
    for inst in plan.to_run:
        print(f"{inst.id}: runs because {inst.reason}")


def _show_version(value: bool) -> None:
    if value:
        print(f"{current().name} {current().version or 'unknown version'}")
        raise typer.Exit(0)


def _root(version: bool = typer.Option(False, "--version", "-V", is_eager=True, callback=_show_version,
                                       help="Print the version and exit.")) -> None:
    """Options before the command."""


def build_app(with_extensions: bool = True) -> typer.Typer:
    app = typer.Typer(help=f"{current().name}: {current().description}",
                      no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False,
                      rich_markup_mode=None, context_settings={"help_option_names": ["-h", "--help"]})
    app.callback()(_root)
    app.command("run")(run)
    app.command("plan")(plan_command)
    app.command("dag")(dag)
    app.command("watch")(watch_command)
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
    previous: dict[int, object] = {}
    try:
        previous = interrupts.install()  # a signal may arrive during it: the caller's handler raises then
        _main(application, argv)
    except interrupts.Interrupted as exc:  # between the handler's installation and _main's own handling
        interrupts.exit_interrupted(application.name, exc)
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
        _whole_short_help(command)
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
        stop = interrupts.requested()
        if stop is not None:  # e.g. an import cut short by the signal
            _fail("interrupted", stop.exit_code)
        _fail(f"unexpected {type(exc).__name__}: {exc} (traceback: {_crash_log()})", 1)
    sys.exit(result if isinstance(result, int) else 0)


def _whole_short_help(group: Any) -> None:
    """Command lists in ``--help`` show each command's first sentence whole (click cuts it at 45
    characters with '...', also when piped)."""
    for command in getattr(group, "commands", {}).values():
        if not command.short_help and command.help:
            command.short_help = command.help.strip().split("\n\n")[0].replace("\n", " ").split(". ")[0].rstrip(".")
        _whole_short_help(command)


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

