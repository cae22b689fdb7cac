"""Code versions: a node's recipe changes when its source does.

The code version of a node type is the sha256 over the AST-normalised source (comments, docstrings
and formatting do not count) of the module defining it and of every module of the app's node packages
(:attr:`.app.App.node_packages`) that it imports, transitively. The engine is left out: engine
changes that affect stored results bump :data:`.hashing.CACHE_FORMAT_SALT` instead. A node
declared with ``version="..."`` uses that string and nothing else.

Parsing every module costs about a second per planning run; a memo (:data:`MEMO_NAME` in the user's
cache folder, :mod:`.userstate`, shared by every result cache) keeps each module's
normalised hash and imported names under the sha256 of its bytes, its name and the interpreter
version, so that a run parses only the files that changed since any earlier run, in whatever cache
folder. Which imported names are tracked modules is decided afresh every run.
"""
from __future__ import annotations

import ast
import hashlib
import importlib.util
import inspect
import sys

from .app import current
from .hashing import digest_fields
from .node import NodeSpec
from .userstate import read_record, write_record

_module_cache: dict[str, tuple[str, tuple[str, ...]]] = {}

MEMO_NAME = "code_versions.json"
MEMO_ENTRIES = 4000  # the most recent entries a saved memo keeps


def _strip_docstrings(tree: ast.AST) -> None:
    for n in ast.walk(tree):
        if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = n.body
            if body and isinstance(body[0], ast.Expr) and isinstance(getattr(body[0], "value", None), ast.Constant) \
                    and isinstance(body[0].value.value, str):
                n.body = body[1:] or [ast.Pass()]


def _tree_hash(tree: ast.Module) -> str:
    _strip_docstrings(tree)
    return hashlib.sha256(ast.dump(tree, include_attributes=False).encode()).hexdigest()


def normalised_source_hash(source: str) -> str:
    """sha256 of the source's AST with docstrings removed (comments and layout never reach it)."""
    return _tree_hash(ast.parse(source))


def _is_tracked(name: str) -> bool:
    return any(name == p or name.startswith(p + ".") for p in current().node_packages)


def _module_exists(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError, AttributeError):
        return False


def _imported_names(tree: ast.Module, modname: str, is_package: bool) -> list[str]:
    """Every module name an import of ``tree`` may refer to (``from a import b``: ``a`` and ``a.b``)."""
    package = modname if is_package else modname.rpartition(".")[0]
    found: set[str] = set()
    for n in ast.walk(tree):
        if isinstance(n, ast.Import):
            found.update(alias.name for alias in n.names)
        elif isinstance(n, ast.ImportFrom):
            base = n.module or ""
            if n.level:
                parts = package.split(".")
                parent = ".".join(parts[: len(parts) - (n.level - 1)])
                base = f"{parent}.{base}" if base else parent
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in n.names)
    return sorted(m for m in found if m)


def _memo_entry(value: object) -> tuple[str, list[str]] | None:
    if (isinstance(value, list) and len(value) == 2 and isinstance(value[0], str)
            and isinstance(value[1], list) and all(isinstance(m, str) for m in value[1])):
        return value[0], value[1]
    return None


def module_hash(modname: str, memo: dict | None = None) -> tuple[str, tuple[str, ...]]:
    """``(normalised source hash, tracked modules it imports)`` of one module; ``memo`` (see the module
    docstring) is read and filled when given."""
    if modname in _module_cache:
        return _module_cache[modname]
    spec = importlib.util.find_spec(modname)
    if spec is None or not spec.origin or not spec.origin.endswith(".py"):
        raise ValueError(f"module {modname} has no Python source; declare the node with version=...")
    with open(spec.origin, "rb") as f:
        raw = f.read()
    is_package = spec.submodule_search_locations is not None
    key = digest_fields([sys.version, modname, str(is_package), hashlib.sha256(raw).hexdigest()])
    entry = _memo_entry(memo.get(key)) if memo is not None else None
    if entry is None:
        tree = ast.parse(raw.decode("utf-8"))
        names = _imported_names(tree, modname, is_package)
        entry = (_tree_hash(tree), names)
        if memo is not None:
            memo[key] = [entry[0], names]
    digest, names = entry
    _module_cache[modname] = (digest, tuple(m for m in names if _is_tracked(m) and _module_exists(m)))
    return _module_cache[modname]


def load_memo() -> dict:
    """The memo saved in the user's cache folder; empty when there is none."""
    return read_record(MEMO_NAME)


def save_memo(memo: dict) -> None:
    """Write ``memo`` (its newest :data:`MEMO_ENTRIES`) atomically into the user's cache folder; a
    folder that cannot take it only costs the next run its parsing."""
    write_record(MEMO_NAME, memo, MEMO_ENTRIES)


def code_version(spec: NodeSpec, memo: dict | None = None) -> str:
    """The code version of a node type (see the module docstring); ``memo`` as for :func:`module_hash`."""
    if spec.version is not None:
        return "pinned:" + spec.version
    root = spec.func.__module__
    if root == "__main__":
        return "source:" + normalised_source_hash(inspect.getsource(spec.func))
    seen: dict[str, str] = {}
    todo = [root]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        digest, deps = module_hash(name, memo)
        seen[name] = digest
        todo.extend(deps)
    return digest_fields(f"{name}={seen[name]}" for name in sorted(seen))
