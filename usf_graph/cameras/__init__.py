"""Camera models: pixel <-> ray in both directions, lens normal maps, calibration files."""

from .base import DEFAULT_ROTATION, Camera
from .cubemap import Cubemap, EquiAngularCubemap, cube_faces
from .files import read_mask
from .fisheye import FOV, Fisheye, KannalaBrandt, RadialPoly
from .formats import from_doc, with_fov_and_mask
from .io import frame_key, imu_rotation, imu_time_shift, load, load_all, load_rig, rig_topics, save
from .omni import EUCM, DoubleSphere, Mei
from .panorama import Equirectangular, LensNormalMap
from .pinhole import Division, Pinhole
from .rig import stitch_at
from .scaramuzza import Scaramuzza

__all__ = ["Camera", "DEFAULT_ROTATION", "Pinhole", "Division", "Fisheye", "KannalaBrandt", "FOV", "RadialPoly", "Mei",
           "DoubleSphere", "EUCM", "Scaramuzza", "Equirectangular", "Cubemap", "EquiAngularCubemap", "cube_faces", "LensNormalMap", "frame_key", "from_doc", "imu_rotation", "imu_time_shift", "load", "load_all", "load_rig", "read_mask", "rig_topics", "save", "stitch_at", "with_fov_and_mask"]
