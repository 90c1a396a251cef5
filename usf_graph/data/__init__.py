"""Spherical samples as PyG data, and PyG transforms on them."""

from ..frontend.image import SphericalImage
from .transforms import (
    GaussianEdgeWeight,
    GeodesicRadiusGraph,
    Level,
    RandomRotation,
    VisibleSubgraph,
    rotate_sample,
)

__all__ = ["SphericalImage", "RandomRotation", "Level", "GeodesicRadiusGraph", "GaussianEdgeWeight",
           "VisibleSubgraph", "rotate_sample"]
