"""Spherical samples as PyG data, and PyG transforms on them."""

from ..frontend.image import SphericalImage
from .transforms import (
    GaussianEdgeWeight,
    GeodesicRadiusGraph,
    RandomRotation,
    VisibleSubgraph,
    rotate_sample,
)

__all__ = ["SphericalImage", "RandomRotation", "GeodesicRadiusGraph", "GaussianEdgeWeight",
           "VisibleSubgraph", "rotate_sample"]
