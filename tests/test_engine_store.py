"""The artifact store: pickle-free round trips, atomic commits, corrupt entries never read."""
from __future__ import annotations

import dataclasses
import json
import os
import threading
import time

import numpy as np
import pytest

from retrotouch.graph.artifacts import ArtifactError
from retrotouch.graph.hashing import file_sha256
from retrotouch.graph.node import Files
from retrotouch.graph.store import CorruptEntry, Store
from retrotouch.nodes.data.types import CurveEnd, Mesh

KEY = "ab" + "0" * 62


def test_round_trip_of_every_supported_kind(tmp_path):
    store = Store(str(tmp_path))
    mesh = Mesh(np.arange(12, dtype=np.float64).reshape(4, 3), np.array([[0, 1, 2], [0, 2, 3]]), "x")
    value = {"mesh": mesh, "end": CurveEnd.LOOP, "t": (1, 2.5, None, True), "nan": float("nan"),
             "s": np.float32(1.5), "files": Files({"a/b.txt": b"hi"}), "list": [np.zeros((0, 3), np.int8), "x"]}
    got = store.load(store.write(KEY, value, info={}))
    assert np.array_equal(got["mesh"].vertices, mesh.vertices) and got["mesh"].faces.dtype == mesh.faces.dtype
    assert got["mesh"].source == "x" and isinstance(got["mesh"], Mesh)
    assert got["end"] is CurveEnd.LOOP
    assert got["t"] == (1, 2.5, None, True) and np.isnan(got["nan"])
    assert got["s"] == np.float32(1.5) and got["s"].dtype == np.float32
    assert got["files"] == Files({"a/b.txt": b"hi"})
    assert got["list"][0].shape == (0, 3) and got["list"][0].dtype == np.int8


@dataclasses.dataclass(frozen=True)
class Foreign:
    x: int


def test_refuses_values_it_cannot_store_without_pickle(tmp_path):
    store = Store(str(tmp_path))
    with pytest.raises(ArtifactError, match="object arrays"):
        store.write(KEY, {"a": np.array([object()])}, info={})
    with pytest.raises(ArtifactError, match="not from a retrotouch module"):
        store.write(KEY, Foreign(1), info={})
    with pytest.raises(ArtifactError, match="dict keys must be str"):
        store.write(KEY, {1: 2}, info={})
    assert store.lookup(KEY) is None
    assert os.listdir(os.path.join(store.root, "tmp")) == []  # failed writes leave nothing behind


def entry_files(store: Store, key: str) -> dict[str, str]:
    folder = store.entry_dir(key)
    return {name: os.path.join(folder, name) for name in os.listdir(folder)}


def test_leftover_temp_dir_of_a_killed_writer_is_not_an_entry(tmp_path):
    store = Store(str(tmp_path))
    ref = store.write(KEY, np.arange(10), info={})
    tmp = os.path.join(store.root, "tmp", "deadbeef")
    os.makedirs(tmp)
    with open(os.path.join(tmp, "a0.npy"), "wb") as f:
        f.write(b"\x93NUMPY partial")
    other = "cd" + "1" * 62
    assert store.lookup(other) is None
    assert store.lookup(KEY) == ref


@pytest.mark.parametrize("damage", ["truncate", "no_meta", "meta_only", "bad_meta"])
def test_damaged_entry_is_a_miss_and_is_removed(tmp_path, damage):
    store = Store(str(tmp_path))
    store.write(KEY, np.arange(1000), info={})
    files = entry_files(store, KEY)
    array = next(p for n, p in files.items() if n.endswith(".npy"))
    if damage == "truncate":
        with open(array, "r+b") as f:
            f.truncate(100)
    elif damage == "no_meta":
        os.remove(files["meta.json"])
    elif damage == "meta_only":
        for name, path in files.items():
            if name != "meta.json":
                os.remove(path)
    else:
        with open(files["meta.json"], "w") as f:
            f.write('{"format": "retrotouch.artifact/1", "key": ')
    assert store.lookup(KEY) is None
    assert not os.path.exists(store.entry_dir(KEY))


def test_same_size_corruption_is_caught_on_load(tmp_path):
    store = Store(str(tmp_path))
    ref = store.write(KEY, np.arange(1000, dtype=np.int64), info={})
    array = next(p for n, p in entry_files(store, KEY).items() if n.endswith(".npy"))
    with open(array, "r+b") as f:
        f.seek(-8, os.SEEK_END)
        f.write(b"\xff" * 8)
    assert store.lookup(KEY) is not None  # sizes still match: the cheap check passes
    with pytest.raises(CorruptEntry, match="sha256"):
        store.load(ref)
    assert store.lookup(KEY) is None  # and the entry is gone, so the node recomputes


def test_a_file_is_hashed_once_per_process_until_it_changes(tmp_path, monkeypatch):
    from retrotouch.graph import store as store_module

    hashed = []
    monkeypatch.setattr(store_module, "file_sha256", lambda path: hashed.append(path) or file_sha256(path))
    store = Store(str(tmp_path))
    ref = store.write(KEY, np.arange(1000, dtype=np.int64), info={})
    files_per_load = len(entry_files(store, KEY)) - 1  # every file but meta.json
    store.load(ref)
    store.load(ref)
    assert len(hashed) == 2 * files_per_load  # written once, checked on the first load only
    array = next(p for n, p in entry_files(store, KEY).items() if n.endswith(".npy"))
    stat = os.stat(array)
    time.sleep(0.05)  # past the file system's timestamp granularity
    with open(array, "r+b") as f:  # same size; the write moves the modification time
        f.seek(-8, os.SEEK_END)
        f.write(b"\xff" * 8)
    assert os.stat(array).st_mtime_ns != stat.st_mtime_ns
    with pytest.raises(CorruptEntry, match="sha256"):
        store.load(ref)
    assert store.lookup(KEY) is None


def test_concurrent_writers_of_one_key_leave_one_sound_entry(tmp_path):
    store = Store(str(tmp_path))
    value = np.arange(200_000, dtype=np.float64)
    refs, errors = [], []

    def writer():
        try:
            refs.append(store.write(KEY, value, info={}))
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=writer) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert len({r.content_sha256 for r in refs}) == 1
    assert np.array_equal(store.load(store.lookup(KEY)), value)
    assert [k for k, _ in store.entries()] == [KEY]
    assert os.listdir(os.path.join(store.root, "tmp")) == []


def test_meta_records_size_and_hash_of_every_file(tmp_path):
    store = Store(str(tmp_path))
    ref = store.write(KEY, {"a": np.ones(3), "b": b"xyz"}, info={"node": "n"})
    with open(os.path.join(ref.path, "meta.json")) as f:
        meta = json.load(f)
    assert meta["key"] == KEY and meta["node"] == "n"
    assert set(meta["files"]) == {n for n in os.listdir(ref.path) if n != "meta.json"}
    assert all(info["size"] == os.path.getsize(os.path.join(ref.path, n)) for n, info in meta["files"].items())
