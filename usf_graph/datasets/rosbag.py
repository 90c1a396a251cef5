r"""A ROS bag's camera frames lifted onto a spherical grid, as a PyG dataset.

The frames of one image topic (:mod:`usf_graph.bags`) go through their camera (a
calibration file, a :class:`~usf_graph.cameras.Camera`, or the bag's ``CameraInfo``) onto the
grid once; the processed file holds only their signal, so a sample carries its ``x`` and
the grid is shared. With an IMU topic every frame also gets its up from the accelerometer.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from .. import bags
from ..cameras import Camera, imu_rotation, imu_time_shift, load
from ..frontend import SphericalFrontend
from ..frontend.image import SphericalImage, unit_range
from ..grids import Grid, from_spec
from ..videos import check_every
from .frames import LiftedFrames, digest


class RosBagFrames(LiftedFrames):
    r"""The frames of a ROS 1 or ROS 2 bag's image topic, lifted onto a grid.

    Args:
        root: where the processed tensors go (``root/processed``).
        bag: a ROS 1 ``.bag``, or a ROS 2 bag's folder (``.db3``, ``.mcap``).
        topic: the image topic; None: the bag's only one.
        camera: a calibration file, a :class:`~usf_graph.cameras.Camera`, or None for the
            bag's ``CameraInfo`` beside the topic.
        grid: grid spec or :class:`~usf_graph.grids.Grid`.
        every: keep every ``every``-th frame.
        interpolation: how the frames are lifted (see :class:`SphericalFrontend`).
        imu: an IMU topic: each frame's up from its accelerometer (the mean over
            ``imu_window_ns`` about the frame's stamp), turned into the camera's sphere frame
            by ``imu_to_sphere`` (``[3, 3]``), or by the camera-IMU extrinsics of the
            calibration file ``camera`` (:func:`usf_graph.cameras.imu_rotation`).
        imu_up: ``"accel"`` (the accelerometer, :class:`~usf_graph.bags.Accelerometer`) or
            ``"orientation"`` (the IMU's attitude estimate,
            :class:`~usf_graph.bags.ImuOrientation`).
        imu_time_shift_ns: added to the frames' stamps to read the IMU's clock; default:
            the calibration file's (:func:`usf_graph.cameras.imu_time_shift`), else 0.

    A sample has ``x [N, C]`` (the image's channels in [0, 1]: RGB, or one for a mono
    camera), ``pos``, ``area``, ``mask [N]`` (the points the camera sees), ``stamp_ns [1]``
    and, with an IMU, ``up [1, 3]``; :attr:`gravity` holds every frame's up. The processed
    file's name hashes the bag's size and time, the camera, the grid and the options, so a
    change rebuilds it.
    """

    def __init__(self, root, bag, topic: str | None = None, camera=None, grid="icosahedral:5",
                 every: int = 1, interpolation: str = "bilinear", imu: str | None = None,
                 imu_to_sphere=None, imu_window_ns: int = 10**8, imu_up: str = "accel",
                 imu_time_shift_ns: int | None = None, transform=None,
                 pre_transform=None, progress: bool = True):
        self.every = check_every(every)
        self.bag = self.source = Path(bag)
        self.interpolation, self.progress = interpolation, progress
        if not bags.is_bag(self.bag) or not self.bag.exists():
            raise FileNotFoundError(f"{bag} is not a ROS bag (.bag, a ROS 2 bag's folder, .db3 "
                                    "or .mcap)" + ("" if self.bag.exists() else ": it does not exist"))
        self.topic = bags.image_topic(self.bag, topic)
        self.grid: Grid = from_spec(grid) if isinstance(grid, str) else grid
        self.camera: Camera = (bags.camera(self.bag, self.topic) if camera is None else
                               camera if isinstance(camera, Camera) else load(camera))
        self.imu, self.imu_window_ns = imu, int(imu_window_ns)
        if imu_up not in bags.IMU_SOURCES:
            raise ValueError(f"imu_up must be 'accel' or 'orientation', got {imu_up!r}")
        self.imu_up, self.imu_to_sphere, self.imu_time_shift_ns = imu_up, None, 0
        if imu is not None:
            if imu_time_shift_ns is None and isinstance(camera, (str, Path)):
                imu_time_shift_ns = imu_time_shift(camera)
            self.imu_time_shift_ns = int(imu_time_shift_ns or 0)
            if imu_to_sphere is None and isinstance(camera, (str, Path)):
                imu_to_sphere = imu_rotation(camera)
            if imu_to_sphere is None:
                raise ValueError("imu needs the IMU's rotation to the camera's sphere frame: "
                                 "give imu_to_sphere, or camera as a calibration file with "
                                 "camera-IMU extrinsics")
            self.imu_to_sphere = np.asarray(imu_to_sphere, np.float64).reshape(3, 3)
        self.frontend = SphericalFrontend(self.camera, self.grid, interpolation=interpolation)
        super().__init__(str(root), transform, pre_transform, log=False)
        self._gravity = self._load()["gravity"]

    @property
    def processed_file_names(self):
        storage = sorted(self.bag.glob("*")) if self.bag.is_dir() else [self.bag]
        key = {"bag": str(self.bag.resolve()), "files": [(p.name, p.stat().st_size, p.stat().st_mtime_ns)
                                                         for p in storage if p.is_file()],
               "topic": self.topic, "camera": self.camera.key(), "grid": self.grid.spec,
               "every": self.every, "interpolation": self.interpolation, "imu": self.imu,
               "imu_to_sphere": None if self.imu_to_sphere is None else self.imu_to_sphere.round(12).tolist(),
               "window": self.imu_window_ns, "imu_up": self.imu_up,
               "shift": self.imu_time_shift_ns}
        return [f"rosbag_{self.bag.stem}_{digest(key)}.pt"]

    extra_fields = ("gravity",)

    def process(self):
        acc = None if self.imu is None else bags.IMU_SOURCES[self.imu_up](self.bag, self.imu)
        xs, stamps, ups = [], [], []
        for f in tqdm(bags.frames(self.bag, self.topic, self.every), desc=f"lifting {self.topic}",
                      disable=not self.progress, leave=False):
            img = f.image
            if img.ndim == 3 and img.shape[2] == 4:
                img = img[..., :3]  # alpha: the frontend's mask covers what a camera sees
            xs.append(self.frontend.lift(unit_range(img)))
            stamps.append(f.stamp_ns)
            if acc is not None:
                ups.append(self.imu_to_sphere @ acc.up(f.stamp_ns + self.imu_time_shift_ns,
                                                       self.imu_window_ns))
        if not xs:
            raise ValueError(f"{self.bag} [{self.topic}] has no frames")
        gravity = torch.as_tensor(np.stack(ups)) if ups else torch.zeros(0, 3, dtype=torch.float64)
        self.store(xs, stamps, gravity=gravity)

    @property
    def gravity(self) -> torch.Tensor:
        """``[S, 3]`` float64: each frame's up from the IMU (the camera's sphere frame)."""
        if self.imu is None:
            raise ValueError("this dataset was made without an IMU topic: give imu= for each "
                             "frame's up")
        return self._gravity

    def get(self, idx: int) -> SphericalImage:
        d = super().get(idx)
        if self.imu is not None:
            d.up = self._gravity[idx].float()[None]
        return d

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({len(self)}, bag={self.bag.name}, topic={self.topic}, "
                f"camera={self.camera!r}, grid={self.grid.spec})")
