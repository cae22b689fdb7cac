"""The application the engine serves, handed over by the application's entry point.

The engine names no application: the program name, the packages whose modules declare node types,
the command-line extensions and the distributions whose versions go into ``manifest.json`` all come
from the :class:`App` passed to :func:`configure` (the entry point does this before anything else;
tasks carry it to worker processes). Environment variables are named after the app:
``<NAME>_CACHE_DIR`` and ``<NAME>_NODE_MODULES``.
"""
from __future__ import annotations

import dataclasses
import os


@dataclasses.dataclass(frozen=True)
class App:
    """What an application tells the engine about itself."""

    name: str
    """Program name: shown in messages and help, prefixes the environment variables."""
    node_packages: tuple[str, ...]
    """Packages whose modules (sub-packages included) declare node types."""
    cli_extensions: tuple[str, ...] = ()
    """Modules exposing ``register(typer_app)`` that add commands; they are not node modules."""
    versioned: tuple[str, ...] = ()
    """Distributions whose installed versions are recorded in ``manifest.json``."""
    description: str = ""
    """One line for ``--help``."""
    version: str = ""
    """What ``--version`` prints after the name."""

    @property
    def env_prefix(self) -> str:
        return self.name.upper().replace("-", "_")

    @property
    def cache_env(self) -> str:
        """Environment variable naming the default cache folder."""
        return self.env_prefix + "_CACHE_DIR"

    @property
    def node_modules_env(self) -> str:
        """Environment variable listing extra node modules (comma-separated importable names)."""
        return self.env_prefix + "_NODE_MODULES"


_current: App | None = None


def configure(app: App) -> None:
    """Make ``app`` the application this process's engine serves."""
    global _current
    _current = app


def current() -> App:
    """The configured application; an error naming the fix when nothing configured one."""
    if _current is None:
        raise RuntimeError("no application configured: call graph.app.configure(App(...)) before using the engine")
    return _current


def user_cache_dir() -> str:
    """The app's folder in the user's cache: ``$XDG_CACHE_HOME/<name>`` (default ``~/.cache/<name>``)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, current().name)
