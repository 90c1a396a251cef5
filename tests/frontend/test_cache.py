"""The geometry cache on its own: a file is trusted only when it holds its own key and finite
values, a cache that cannot write still serves, and ``clear`` empties memory and disk."""

import inspect
import warnings

import numpy as np
import pytest
import torch

from tests.helpers import CodeOnLoad
from usf_graph.frontend import GeometryCache, default_cache
from usf_graph.frontend.cache import default_cache_dir


def _builder(value):
    def build():
        build.calls += 1
        return {"w": torch.tensor(value)}
    build.calls = 0
    return build


def _rebuilt(cache, kind, key, build):
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        line = inspect.currentframe().f_lineno + 1
        out = cache.get(kind, key, build)
    assert all((x.filename, x.lineno) == (__file__, line) for x in w)  # the caller's line
    return out, [str(x.message) for x in w]


def test_files_with_another_key_or_non_finite_values_are_rebuilt(tmp_path):
    a, b = {"n": 1}, {"n": 2}
    GeometryCache(tmp_path).get("t", a, _builder([1.0, 2.0]))
    GeometryCache(tmp_path).get("t", b, _builder([3.0, 4.0]))
    path_a, path_b = GeometryCache(tmp_path).path("t", a), GeometryCache(tmp_path).path("t", b)
    path_a.write_bytes(path_b.read_bytes())  # b's entry under a's name
    build = _builder([1.0, 2.0])
    out, said = _rebuilt(GeometryCache(tmp_path), "t", a, build)
    assert build.calls == 1 and out["w"].tolist() == [1.0, 2.0]
    assert any("corrupt or stale (key mismatch); rebuilding it" in m for m in said)
    # the rebuilt entry was written back: a later process reads it without building
    again = _builder([9.0])
    assert GeometryCache(tmp_path).get("t", a, again)["w"].tolist() == [1.0, 2.0]
    assert again.calls == 0
    with np.load(path_a) as z:  # a file of its key whose values went bad
        np.savez(tmp_path / "nan.npz", __key__=z["__key__"], w=np.array([1.0, np.nan]))
    (tmp_path / "nan.npz").replace(path_a)
    build = _builder([1.0, 2.0])
    out, said = _rebuilt(GeometryCache(tmp_path), "t", a, build)
    assert build.calls == 1 and out["w"].tolist() == [1.0, 2.0]
    assert any("non-finite values in 'w'" in m for m in said)


def test_a_cache_that_cannot_write_serves_from_memory(tmp_path):
    (tmp_path / "not_a_dir").write_text("a file where the cache's folder would be")
    cache = GeometryCache(tmp_path / "not_a_dir")
    build = _builder([5.0])
    out, said = _rebuilt(cache, "t", {"n": 1}, build)
    assert out["w"].tolist() == [5.0] and any("could not write geometry cache" in m for m in said)
    assert cache.get("t", {"n": 1}, build)["w"].tolist() == [5.0] and build.calls == 1


@pytest.mark.parametrize("disk", [False, True])
def test_clear_empties_memory_and_with_disk_the_files(tmp_path, disk):
    cache = GeometryCache(tmp_path)
    build = _builder([1.0])
    cache.get("t", {"n": 1}, build)
    cache.clear(disk=disk)
    assert len(list(tmp_path.glob("*.npz"))) == (0 if disk else 1)
    cache.get("t", {"n": 1}, build)
    assert build.calls == 1 + disk  # memory is gone either way; the file served if kept


@pytest.mark.parametrize("value", ["off", "OFF ", "none", "0", ""])
def test_the_environment_turns_the_disk_cache_off(monkeypatch, value):
    monkeypatch.setenv("USF_GRAPH_CACHE", value)
    assert default_cache_dir() is None and GeometryCache().directory is None


def test_the_cache_folder_comes_from_the_environment_or_the_home(monkeypatch, tmp_path):
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setenv("USF_GRAPH_CACHE", "~/geometry")
    assert default_cache_dir() == tmp_path / "geometry"
    monkeypatch.delenv("USF_GRAPH_CACHE")
    assert default_cache_dir() == tmp_path / ".cache" / "usf_graph"


def test_memory_only_cache_counts_builds_and_hits_and_evicts_the_least_recent():
    cache = GeometryCache(None)
    assert cache.path("t", {"n": 0}) is None and (cache.builds, cache.hits) == (0, 0)
    builds = [_builder([float(n)]) for n in range(34)]
    for n in range(32):
        cache.get("t", {"n": n}, builds[n])
    assert (cache.builds, cache.hits) == (32, 0)
    cache.get("t", {"n": 0}, builds[0])  # a hit makes key 0 the most recent
    assert (cache.builds, cache.hits) == (32, 1)
    cache.get("t", {"n": 32}, builds[32])  # 33 entries: key 1, the least recent, goes
    cache.get("t", {"n": 0}, builds[0])
    cache.get("t", {"n": 1}, builds[1])
    assert builds[0].calls == 1 and builds[1].calls == 2 and cache.builds == 34


def test_keys_are_order_free_and_files_named_by_32_hex_digits(tmp_path):
    cache = GeometryCache(tmp_path)
    assert cache.digest("t", {"a": 1, "b": 2}) == cache.digest("t", {"b": 2, "a": 1})
    assert cache.digest("t", {"a": 1}) != cache.digest("u", {"a": 1})
    name = cache.path("t", {"a": 1}).name
    assert name == f"t-{cache.digest('t', {'a': 1})[:32]}.npz"
    build = _builder([1.0])
    cache.get("t", {"a": 1}, build)
    fresh = GeometryCache(tmp_path)
    assert fresh.get("t", {"a": 1}, build)["w"].tolist() == [1.0] and (fresh.builds, fresh.hits) == (0, 1)


def test_clear_keeps_the_files_by_default(tmp_path):
    cache = GeometryCache(tmp_path)
    cache.get("t", {"n": 1}, _builder([1.0]))
    cache.clear()
    assert len(list(tmp_path.glob("*.npz"))) == 1


def test_a_file_holding_pickled_objects_is_not_unpickled(tmp_path):
    cache = GeometryCache(tmp_path)
    path, key = cache.path("t", {"n": 1}), cache.digest("t", {"n": 1})
    mark = tmp_path / "ran"
    np.savez(path, __key__=np.array(key), w=np.array([CodeOnLoad(mark)], dtype=object))
    build = _builder([1.0])
    out, said = _rebuilt(GeometryCache(tmp_path), "t", {"n": 1}, build)
    assert out["w"].tolist() == [1.0] and build.calls == 1 and "corrupt or stale" in said[0]
    assert not mark.exists()  # a cache file never runs code


def test_the_process_wide_cache_is_one_cache():
    assert isinstance(default_cache(), GeometryCache) and default_cache() is default_cache()
