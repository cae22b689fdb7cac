"""Node discovery: every module of the app's node packages registers its node types.

Nobody edits a list: :func:`load` walks the packages named in :attr:`.app.App.node_packages`
(sub-packages included, found with ``pkgutil.walk_packages``, so it works from a source checkout and
from site-packages alike) and fills :data:`.node.REGISTRY`. The app's command-line extension
modules (:attr:`.app.App.cli_extensions`) are not node modules and are skipped. Extra node modules
(tests, benchmarks, plugins) are named in the environment variable ``<APP>_NODE_MODULES``
(comma-separated importable module names).

To keep a fully cached run fast, :func:`load` can be told which node types a pipeline needs: it
then imports only the modules whose source mentions those type names (a text scan), and falls
back to importing everything when a name is not found. Node modules must import cheaply anyway:
import heavy libraries inside the node functions.
"""
from __future__ import annotations

import importlib
import importlib.util
import os
import pkgutil
import re
from typing import Iterable

from .app import current
from .errors import UserError
from .node import REGISTRY, NodeSpec

_TYPE_NAME = re.compile(r"""\bnode\(\s*["']([A-Za-z0-9_.\-]+)["']""")
_imported: set[str] = set()


def extra_modules() -> list[str]:
    """Module names from ``$<APP>_NODE_MODULES``."""
    return [m.strip() for m in os.environ.get(current().node_modules_env, "").split(",") if m.strip()]


def package_sources(package_name: str) -> dict[str, str | None]:
    """Every module of a package and its sub-packages -> its source file (None without .py source)."""
    package = importlib.import_module(package_name)
    out: dict[str, str | None] = {}
    for info in pkgutil.walk_packages(package.__path__, package_name + "."):
        if info.ispkg or info.name.rpartition(".")[2] == "__main__":
            continue
        source = os.path.join(getattr(info.module_finder, "path", ""), info.name.rpartition(".")[2] + ".py")
        out[info.name] = source if os.path.isfile(source) else None
    return out


def node_module_sources() -> dict[str, str | None]:
    """Every node module name -> its source file (None when it has no readable .py source)."""
    app = current()
    out: dict[str, str | None] = {}
    for package_name in app.node_packages:
        out.update({name: src for name, src in package_sources(package_name).items() if name not in app.cli_extensions})
    for name in extra_modules():
        try:
            spec = importlib.util.find_spec(name)
        except (ImportError, ValueError):
            spec = None
        if spec is None:
            raise UserError(f"{current().node_modules_env} names module {name!r}, which cannot be found on sys.path")
        out[name] = spec.origin if spec.origin and spec.origin.endswith(".py") else None
    return out


def _import(name: str) -> None:
    if name in _imported:
        return
    try:
        importlib.import_module(name)
    except UserError:
        raise
    except Exception as exc:  # a broken node module must be named, not hidden in a traceback
        raise UserError(f"cannot import node module {name}: {type(exc).__name__}: {exc}") from exc
    _imported.add(name)


def _declared_types(source: str | None) -> set[str]:
    if source is None:
        return set()
    with open(source, encoding="utf-8") as f:
        return set(_TYPE_NAME.findall(f.read()))


def load(types: Iterable[str] | None = None, modules: Iterable[str] = ()) -> dict[str, NodeSpec]:
    """Fill and return the registry.

    ``types``: import only what is needed for these node types (all modules if None or if one of
    them is not found by the text scan). ``modules``: extra modules to import first (the engine
    passes the client's extra modules to its workers this way).
    """
    for name in modules:
        _import(name)
    wanted = set(types) if types is not None else None
    if wanted is not None and all(t in REGISTRY for t in wanted):
        return REGISTRY
    sources = node_module_sources()
    if wanted is not None:
        pending = {t for t in wanted if t not in REGISTRY}
        chosen = [m for m, src in sources.items() if pending & _declared_types(src)]
        for name in chosen:
            _import(name)
        if all(t in REGISTRY for t in wanted):
            return REGISTRY
    for name in sources:
        _import(name)
    return REGISTRY
