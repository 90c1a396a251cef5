"""Models built from usf_graph.nn layers, and planar baselines."""

from .classifier import PlanarCNN, SphericalClassifier, grid_graph

__all__ = ["SphericalClassifier", "PlanarCNN", "grid_graph"]
