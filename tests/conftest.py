import os
import shutil
import tempfile

_CACHE: list[str] = []


def pytest_configure(config):
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
