"""The package layout ARCHITECTURE.md describes: stage folders, one-way imports, an engine that
names no app, modules and functions of readable size."""
from __future__ import annotations

import ast
import re
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = {"data", "geometry"}
STAGES = {"mesh", "regions", "curves", "layout", "fab", "projection", "preview", "sensing"}
MAX_MODULE_LINES = 400


def _modules(folder: str) -> list[Path]:
    return sorted(p for p in (REPO / folder).rglob("*.py") if "__pycache__" not in p.parts)


def _imported_packages(path: Path) -> set[str]:
    """Sub-packages of nodes/ that a module under nodes/ imports (relative or absolute)."""
    tree = ast.parse(path.read_text())
    here = path.relative_to(REPO / "nodes").parts[:-1]
    found = set()
    for n in ast.walk(tree):
        if isinstance(n, ast.ImportFrom):
            if n.level:
                base = list(here[: len(here) - (n.level - 1)]) if n.level - 1 <= len(here) else None
                if base is None:
                    continue  # beyond nodes/: the engine
                parts = base + (n.module.split(".") if n.module else [])
            elif n.module and n.module.startswith("retrotouch.nodes."):
                parts = n.module.split(".")[2:]
            else:
                continue
            if parts:
                found.add(parts[0])
    return found


def test_nodes_has_one_folder_per_stage_plus_shared_data_and_geometry():
    folders = {p.name for p in (REPO / "nodes").iterdir() if p.is_dir() and p.name != "__pycache__"}
    assert folders == STAGES | SHARED
    loose = {p.name for p in (REPO / "nodes").glob("*.py")}
    assert loose == {"__init__.py", "__main__.py", "app.py"}


def test_every_stage_package_is_installed():
    packages = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    assert {f"retrotouch.nodes.{name}" for name in STAGES | SHARED} <= packages


def test_stages_import_only_shared_packages_and_themselves():
    for path in _modules("nodes"):
        rel = path.relative_to(REPO / "nodes").parts
        if len(rel) == 1:
            continue  # app.py wires the stages together
        own = rel[0]
        allowed = {"geometry"} if own == "geometry" else SHARED if own == "data" else {own} | SHARED
        assert _imported_packages(path) <= allowed, f"{path.relative_to(REPO)} imports {_imported_packages(path) - allowed}"


def test_the_engine_names_no_app():
    for path in _modules("graph"):
        text = path.read_text()
        assert "retrotouch" not in text, f"{path.relative_to(REPO)} names the app"
        assert not re.search(r"\b(trimesh|pymeshlab|millimet)", text), f"{path.relative_to(REPO)} names app specifics"


MAX_FUNCTION_LINES = 80


def test_functions_stay_readable():
    for path in _modules("graph") + _modules("nodes"):
        for n in ast.walk(ast.parse(path.read_text())):
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = n.end_lineno - n.lineno + 1
                assert lines <= MAX_FUNCTION_LINES, \
                    f"{path.relative_to(REPO)}:{n.lineno} {n.name} has {lines} lines (at most {MAX_FUNCTION_LINES})"


def test_modules_stay_readable():
    for path in _modules("graph") + _modules("nodes"):
        lines = len(path.read_text().splitlines())
        assert lines <= MAX_MODULE_LINES, f"{path.relative_to(REPO)} has {lines} lines (at most {MAX_MODULE_LINES})"
