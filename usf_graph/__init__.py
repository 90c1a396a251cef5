"""usf-graph: the Unified Spherical Frontend for PyTorch Geometric.

The subpackages load on first use, so ``import usf_graph`` does not import torch, PyG,
OpenCV or SciPy until something needs them.
"""

import importlib

from ._version import __version__

_SUBPACKAGES = ("cameras", "data", "datasets", "frontend", "geometry", "graph", "grids",
                "models", "nn", "scenes", "sparse", "testing", "train", "viz")
__all__ = ["cameras", "geometry", "grids", "SphericalFrontend", "SphericalImage", "__version__"]


def __getattr__(name: str):
    if name in _SUBPACKAGES:
        return importlib.import_module(f"{__name__}.{name}")
    if name == "SphericalFrontend":
        from .frontend import SphericalFrontend as value
    elif name == "SphericalImage":
        from .frontend.image import SphericalImage as value
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value  # loaded once; tools that read the module's dict (pdoc) see it
    return value
