import os
import tempfile


def pytest_configure(config):
    # tests must not read or fill the user's geometry cache
    os.environ["USF_GRAPH_CACHE"] = tempfile.mkdtemp(prefix="usf_graph_test_cache_")
