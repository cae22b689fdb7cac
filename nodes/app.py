"""The ``retrotouch`` application: what it tells the engine about itself, and its entry point."""
from __future__ import annotations

import importlib.metadata
from pathlib import Path

from ..graph.app import App


def _version() -> str:
    """The installed distribution's version, or pyproject.toml's in a source checkout."""
    try:
        return importlib.metadata.version("retrotouch")
    except importlib.metadata.PackageNotFoundError:
        import tomllib

        try:
            project = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"]
            return f"{project['version']} (source checkout)"
        except (OSError, KeyError, ValueError):
            return "unknown version (not installed)"


APP = App(
    name="retrotouch",
    description="retrofit 3D objects with surface-conforming touch sensing.",
    version=_version(),
    node_packages=(__package__,),
    cli_extensions=(f"{__package__}.sensing.cli", f"{__package__}.projection.cli"),
    versioned=("numpy", "scipy", "trimesh", "pymeshlab", "potpourri3d", "ortools", "shapely"),
)


def main(argv: list[str] | None = None) -> None:
    """``retrotouch ...``: the engine's command line with the sensing and projection commands."""
    from ..graph import interrupts

    try:
        if argv is None:  # this process's own command line: Ctrl-C from the first moment is one clean line
            interrupts.install()
        from ..graph.cli import main as engine_main

        engine_main(APP, argv)
    except interrupts.Interrupted as exc:  # before the engine's own handling is in place
        interrupts.exit_interrupted(APP.name, exc)
