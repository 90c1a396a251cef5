"""From images to spherical graphs: interpolation tables, field of view, cache, rendering,
rigs, and lifted samples on disk."""

from .cache import GeometryCache, default_cache
from .frontend import SphericalFrontend, default_radius, grid_graph
from .lifted import load_lifted, read_lifted, save_lifted
from .reimage import Reimager, render
from .rig import RigFrontend, RigReimager, blend_weights, choose_distance, render_rig

__all__ = ["SphericalFrontend", "RigFrontend", "Reimager", "RigReimager", "choose_distance", "render_rig", "blend_weights", "GeometryCache", "default_cache",
           "default_radius", "grid_graph", "render", "save_lifted", "load_lifted", "read_lifted"]
