"""From images to spherical graphs: interpolation tables, field of view, cache, rendering."""

from .cache import GeometryCache, default_cache
from .frontend import SphericalFrontend, default_radius, grid_graph, render
from .rig import RigFrontend

__all__ = ["SphericalFrontend", "RigFrontend", "GeometryCache", "default_cache", "default_radius", "grid_graph",
           "render"]
