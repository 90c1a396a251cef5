"""Spherical samples as PyG data, and PyG transforms on them."""

from ..frontend.image import SphericalImage
from .transforms import GeodesicRadiusGraph, RandomRotation, rotate_sample

__all__ = ["SphericalImage", "RandomRotation", "GeodesicRadiusGraph", "rotate_sample"]
