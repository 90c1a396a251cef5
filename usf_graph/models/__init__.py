"""Models built from usf_graph.nn layers, and planar baselines."""

from .classifier import PlanarCNN, SphericalClassifier, grid_graph
from .detector import SphericalDetector
from .planar_detector import PlanarDetector
from .pointcloud import PointCloudNet, PointNet

__all__ = ["SphericalClassifier", "PlanarCNN", "grid_graph", "PointCloudNet", "PointNet",
           "SphericalDetector", "PlanarDetector"]
