"""usf-graph: the Unified Spherical Frontend for PyTorch Geometric."""

__version__ = "0.1.0"

from . import cameras, geometry, grids  # noqa: E402
from .data import SphericalImage  # noqa: E402
from .frontend import SphericalFrontend  # noqa: E402

__all__ = ["cameras", "geometry", "grids", "SphericalFrontend", "SphericalImage", "__version__"]
