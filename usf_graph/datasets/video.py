r"""A video's frames lifted onto a spherical grid, as a PyG dataset: one camera's video, or
a 360 camera's whose frames hold its cameras side by side (a rig, ``split=True``)."""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from pathlib import Path

import torch
from tqdm.auto import tqdm

from .. import videos
from ..cameras import Camera, load, load_rig
from ..frontend import RigFrontend, SphericalFrontend
from ..frontend.image import SphericalImage, unit_range
from ..grids import Grid, from_spec
from .frames import LiftedFrames, digest


class VideoFrames(LiftedFrames):
    r"""The frames of a video, lifted onto a grid.

    Args:
        root: where the processed tensors go (``root/processed``).
        video: the video file (any format OpenCV decodes: ``.mp4``, ``.avi``, ...).
        camera: a calibration file or a :class:`~usf_graph.cameras.Camera`; with ``split``,
            a rig: its calibration file (:func:`~usf_graph.cameras.load_rig`) or
            ``{name: Camera}``.
        grid: grid spec or :class:`~usf_graph.grids.Grid`.
        every: keep every ``every``-th frame.
        interpolation: how the frames are lifted (see :class:`SphericalFrontend`).
        split: each frame holds the rig's cameras' images side by side, in its order (a
            dual-fisheye 360 camera's video), lifted together onto one sphere
            (:class:`~usf_graph.frontend.RigFrontend`).
        fov_deg: the usable field of view of every camera loaded from a file (a 190-degree
            fisheye calibrated as Kannala-Brandt may claim 270).
        blend, distance: how a rig's cameras are stitched (:class:`RigFrontend`).
        eye: ``"left"`` or ``"right"``: of a stereo 360 video, that eye's panorama of each
            frame (the layout from its 360 metadata, :func:`usf_graph.videos.stereo_layout`).

    A sample has ``x [N, C]`` (RGB in [0, 1]), ``pos``, ``area``, ``mask [N]`` (the points
    the camera sees), ``frame [1]`` (its index in the video) and ``stamp_ns [1]`` (its time
    from the video's start, by the frame rate in its header; -1, with a warning, where the
    header has none). The processed file's name
    hashes the video's path, size and time, the camera, the grid and the options, so a
    change rebuilds it.
    """

    def __init__(self, root, video, camera, grid="icosahedral:5", every: int = 1,
                 interpolation: str = "bilinear", split: bool = False, fov_deg: float | None = None,
                 blend: str = "best", distance: float | None = None, eye: str | None = None,
                 transform=None, pre_transform=None, progress: bool = True):
        self.video = self.source = Path(video)
        if not self.video.is_file():
            raise FileNotFoundError(f"video {video} does not exist")
        if not videos.is_video(self.video):
            raise ValueError(f"{video} is not named as a video ({', '.join(videos.VIDEO_SUFFIXES)})")
        self.every, self.interpolation, self.split, self.progress = \
            videos.check_every(every), interpolation, split, progress
        self.grid: Grid = from_spec(grid) if isinstance(grid, str) else grid
        self.eye = eye
        if eye is not None:  # refused now where the video has no stereo layout
            videos.stereo_layout(self.video, eye)
        if split:
            rig = camera if isinstance(camera, Mapping) else load_rig(camera)
            if fov_deg is not None:
                rig = {n: c.with_fov(fov_deg) for n, c in rig.items()}
            self.cameras: dict[str, Camera] = dict(rig)
            self.frontend = RigFrontend(self.cameras, self.grid, interpolation=interpolation,
                                        blend=blend, distance=distance)
        else:
            if isinstance(camera, Mapping):
                raise ValueError("a rig's cameras are lifted from frames that hold them side by "
                                 "side: give split=True, or one camera")
            cam = camera if isinstance(camera, Camera) else load(camera)
            if cam.model == "equirectangular":  # refused where its 360 metadata says stereo
                videos.check_panorama_video(self.video, eye)
            self.cameras = {"camera": cam.with_fov(fov_deg) if fov_deg is not None else cam}
            self.frontend = SphericalFrontend(self.cameras["camera"], self.grid,
                                              interpolation=interpolation)
        self.fps = videos.info(self.video)[0]
        # eye only where given, so that the mono videos' processed files keep their names
        self._options = {"blend": blend, "distance": distance, **({"eye": eye} if eye else {})}
        super().__init__(str(root), transform, pre_transform, log=False)
        self.frame = self._load()["frame"]

    extra_fields = ("frame",)

    @property
    def processed_file_names(self):
        st = self.video.stat()
        key = {"video": str(self.video.resolve()), "size": st.st_size, "mtime": st.st_mtime_ns,
               "cameras": {n: c.key() for n, c in self.cameras.items()}, "grid": self.grid.spec,
               "every": self.every, "interpolation": self.interpolation, "split": self.split,
               **self._options}
        return [f"video_{self.video.stem}_{digest(key)}.pt"]

    def process(self):
        xs, stamps, index = [], [], []
        count = len(self.cameras)
        for i, rgb in tqdm(videos.frames(self.video, self.every, self.eye), desc=f"lifting {self.video.name}",
                           disable=not self.progress, leave=False):
            img = unit_range(rgb)
            if self.split:
                xs.append(self.frontend.lift(videos.split_frame(img, count, str(self.video))))
            else:
                xs.append(self.frontend.lift(img))
            index.append(i)
            stamps.append(round(i / self.fps * 1e9) if self.fps > 0 else -1)
        if self.fps <= 0:
            warnings.warn(f"{self.video}'s header gives no frame rate, so its frames have no "
                          "time: stamp_ns is -1 for each; use frame (its index)", stacklevel=2)
        self.store(xs, stamps, frame=torch.as_tensor(index, dtype=torch.int64))

    def get(self, idx: int) -> SphericalImage:
        d = super().get(idx)
        d.frame = self.frame[idx].reshape(1)
        return d

    def __repr__(self) -> str:
        cams = ", ".join(self.cameras) if self.split else repr(self.cameras["camera"])
        return (f"{type(self).__name__}({len(self)}, video={self.video.name}, "
                f"{'rig=[' + cams + ']' if self.split else 'camera=' + cams}, grid={self.grid.spec})")


__all__ = ["VideoFrames"]
