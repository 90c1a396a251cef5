"""PyG datasets for the tasks."""

from .mnist import SphericalMNIST, download_mnist, load_digits, read_idx, read_mnist_csv
from .pandora import Pandora, read_annotations
from .pointcloud import SHAPES, ModelNet, ProceduralShapes, make_shape, read_off, sample_surface
from .rooms import RoomsDetection, RoomsGravity, RoomsSegmentation
from .rosbag import RosBagFrames
from .stanford import Stanford2D3DS
from .video import VideoFrames
from .woodscape import WoodScape

__all__ = ["SphericalMNIST", "download_mnist", "load_digits", "read_idx", "read_mnist_csv", "ModelNet",
           "ProceduralShapes", "Pandora", "read_annotations", "RoomsDetection", "RoomsGravity", "RoomsSegmentation", "RosBagFrames", "VideoFrames", "Stanford2D3DS", "WoodScape", "SHAPES", "make_shape", "read_off", "sample_surface"]
