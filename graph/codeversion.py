"""Code versions: a node's recipe changes when its source does.

The code version of a node type is the sha256 over the AST-normalised source (comments, docstrings
and formatting do not count) of the module defining it and of every module of the app's node packages
(:attr:`.app.App.node_packages`) that it imports, transitively. The engine is left out: engine
changes that affect stored results bump :data:`.hashing.CACHE_FORMAT_SALT` instead. A node
declared with ``version="..."`` uses that string and nothing else.
"""
from __future__ import annotations

import ast
import hashlib
import importlib.util
import inspect

from .app import current
from .hashing import digest_fields
from .node import NodeSpec

_module_cache: dict[str, tuple[str, tuple[str, ...]]] = {}


def _strip_docstrings(tree: ast.AST) -> None:
    for n in ast.walk(tree):
        if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = n.body
            if body and isinstance(body[0], ast.Expr) and isinstance(getattr(body[0], "value", None), ast.Constant) \
                    and isinstance(body[0].value.value, str):
                n.body = body[1:] or [ast.Pass()]


def normalised_source_hash(source: str) -> str:
    """sha256 of the source's AST with docstrings removed (comments and layout never reach it)."""
    tree = ast.parse(source)
    _strip_docstrings(tree)
    return hashlib.sha256(ast.dump(tree, include_attributes=False).encode()).hexdigest()


def _is_tracked(name: str) -> bool:
    return any(name == p or name.startswith(p + ".") for p in current().node_packages)


def _module_exists(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError, AttributeError):
        return False


def _imports(tree: ast.Module, modname: str, is_package: bool) -> set[str]:
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
    return {m for m in found if m and _is_tracked(m) and _module_exists(m)}


def module_hash(modname: str) -> tuple[str, tuple[str, ...]]:
    """``(normalised source hash, tracked modules it imports)`` of one module."""
    if modname in _module_cache:
        return _module_cache[modname]
    spec = importlib.util.find_spec(modname)
    if spec is None or not spec.origin or not spec.origin.endswith(".py"):
        raise ValueError(f"module {modname} has no Python source; declare the node with version=...")
    with open(spec.origin, encoding="utf-8") as f:
        tree_source = f.read()
    digest = normalised_source_hash(tree_source)
    deps = tuple(sorted(_imports(ast.parse(tree_source), modname, spec.submodule_search_locations is not None)))
    _module_cache[modname] = (digest, deps)
    return _module_cache[modname]


def code_version(spec: NodeSpec) -> str:
    """The code version of a node type (see the module docstring)."""
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
        digest, deps = module_hash(name)
        seen[name] = digest
        todo.extend(deps)
    return digest_fields(f"{name}={seen[name]}" for name in sorted(seen))
