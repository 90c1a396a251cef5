"""Models built from usf_graph.nn layers, and planar baselines."""

from .classifier import PlanarCNN, SphericalClassifier, grid_graph
from .deeplab import SphericalDeepLabV3
from .detector import SphericalDetector
from .gravity import EdgeVotes, GravityHead, UpPolish
from .planar_detector import PlanarDetector
from .planar_seg import PlanarDeepLab, PlanarUNet
from .pointcloud import PointCloudNet, PointNet
from .sign import SignCheck, set_sign_check
from .unet import SphericalBackbone, SphericalUNet
from .upnet import UpNet, set_level_prior

__all__ = ["SphericalClassifier", "PlanarCNN", "grid_graph", "PointCloudNet", "PointNet",
           "SphericalDetector", "PlanarDetector", "SphericalBackbone", "SphericalUNet",
           "PlanarUNet", "PlanarDeepLab", "SphericalDeepLabV3", "GravityHead", "EdgeVotes", "UpPolish", "UpNet",
           "set_level_prior", "SignCheck", "set_sign_check"]
