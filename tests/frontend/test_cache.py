"""The geometry cache on its own: a file is trusted only when it holds its own key and finite
values, a cache that cannot write still serves, and ``clear`` empties memory and disk."""

import warnings

import numpy as np
import pytest
import torch

from usf_graph.frontend import GeometryCache


def _builder(value):
    def build():
        build.calls += 1
        return {"w": torch.tensor(value)}
    build.calls = 0
    return build


def _rebuilt(cache, kind, key, build):
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        out = cache.get(kind, key, build)
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
