import os
import shutil
import tempfile

import pytest

_CACHE: list[str] = []


#: What a run writes at most: a geometry cache per worker (about 300 MB) and its tmp_paths.
NEEDS_MB = 1024


def pytest_configure(config):
    # a full disk fails the run deep in pytest's machinery, without saying why: say it first
    free = shutil.disk_usage(tempfile.gettempdir()).free // 2**20
    if free < NEEDS_MB and not os.environ.get("PYTEST_XDIST_WORKER"):
        raise pytest.UsageError(f"only {free} MB free in {tempfile.gettempdir()}: the tests write "
                                f"up to {NEEDS_MB} MB there; free some space (or set TMPDIR)")
    # tests must not read or fill the user's geometry cache
    _CACHE.append(tempfile.mkdtemp(prefix="usf_graph_test_cache_"))
    os.environ["USF_GRAPH_CACHE"] = _CACHE[-1]
    if os.environ.get("PYTEST_XDIST_WORKER"):  # one thread per worker: the workers share the cores
        import torch

        torch.set_num_threads(1)


def pytest_unconfigure(config):
    # each run's cache is a few hundred MB: left behind, runs fill the disk
    while _CACHE:
        shutil.rmtree(_CACHE.pop(), ignore_errors=True)
