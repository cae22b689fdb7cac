"""Shared test setup.

Tests import the installed package (``retrotouch.graph``, ``retrotouch.nodes``), never the repo's
``graph/``/``nodes/`` folders directly, so they run the same against an editable and a regular
install. Repo files (pipelines, meshes) are located from this file's position.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from retrotouch.graph.app import configure
from retrotouch.nodes.app import APP

configure(APP)  # in-process engine calls (run_pipeline, make_plan, registry) serve retrotouch

REPO = Path(__file__).resolve().parents[1]
ENGINE_NODES = REPO / "tests" / "engine_nodes"
"""Tiny node types for engine tests (module ``rt_testnodes``)."""


@pytest.fixture(autouse=True, scope="session")
def user_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The engine's per-user records (code-version memo, task durations) in a folder of this test
    session, for every test and every process it starts: none of the user's own, none left to them."""
    folder = tmp_path_factory.mktemp("user-cache")
    previous = os.environ.get("XDG_CACHE_HOME")
    os.environ["XDG_CACHE_HOME"] = str(folder)
    yield folder
    if previous is None:
        os.environ.pop("XDG_CACHE_HOME", None)
    else:
        os.environ["XDG_CACHE_HOME"] = previous


@pytest.fixture
def repo() -> Path:
    return REPO


@pytest.fixture
def test_nodes(monkeypatch: pytest.MonkeyPatch):
    """Register the engine test node types in this process and in any subprocess or dask worker
    started from it (through PYTHONPATH and RETROTOUCH_NODE_MODULES)."""
    monkeypatch.syspath_prepend(str(ENGINE_NODES))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(ENGINE_NODES), os.environ.get("PYTHONPATH")])))
    monkeypatch.setenv("RETROTOUCH_NODE_MODULES", "rt_testnodes")
    import rt_testnodes  # noqa: F401  (registers the t.* node types)

    return rt_testnodes


@pytest.fixture
def cli(tmp_path: Path):
    """Run ``retrotouch ARGS`` in a subprocess (cwd: tmp_path) and return the CompletedProcess."""

    def run(*args: str, cwd: Path | None = None, env: dict[str, str] | None = None, timeout: float = 300):
        full_env = {**os.environ, **(env or {})}
        return subprocess.run([sys.executable, "-m", "retrotouch.nodes", *map(str, args)], cwd=cwd or tmp_path,
                              env=full_env, capture_output=True, text=True, timeout=timeout)

    return run


@pytest.fixture(scope="session")
def default_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The README's main job, run once per test session with a fresh cache: ``retrotouch run
    pipelines/retrofit.yaml`` in a new folder (cache in ``./cache``, outputs in ``./out``).
    Returns that folder; tests that run more commands in it must leave ``out/sensing_map.json``."""
    workdir = tmp_path_factory.mktemp("default_run")
    result = subprocess.run([sys.executable, "-m", "retrotouch.nodes", "run", str(REPO / "pipelines" / "retrofit.yaml"),
                             "--out", "out"], cwd=workdir, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    (workdir / "first_run.stdout").write_text(result.stdout)
    return workdir
