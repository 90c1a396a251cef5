import os
import tempfile


def pytest_configure(config):
    # tests must not read or fill the user's geometry cache
    os.environ["USF_GRAPH_CACHE"] = tempfile.mkdtemp(prefix="usf_graph_test_cache_")
    if os.environ.get("PYTEST_XDIST_WORKER"):  # one thread per worker: the workers share the cores
        import torch

        torch.set_num_threads(1)
