"""Models built from usf_graph.nn layers, and planar baselines."""

from .classifier import PlanarCNN, SphericalClassifier, grid_graph
from .pointcloud import PointCloudNet, PointNet

__all__ = ["SphericalClassifier", "PlanarCNN", "grid_graph", "PointCloudNet", "PointNet"]
