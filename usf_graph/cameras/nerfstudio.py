"""Nerfstudio's ``transforms.json`` (and Instant-NGP's, which it grew from): the camera of
a NeRF or Gaussian-splatting capture, given once for every frame or per frame.

Its intrinsics are COLMAP's, written as nerfstudio's ``ns-process-data`` copies them
(``fl_x fl_y cx cy``, ``k1 k2 k3 k4 p1 p2``, ``camera_model``), principal point included, so
they are read through :func:`~usf_graph.cameras.colmap.colmap_camera` and its half-pixel
convention. ``file_path`` names a frame (the key of a file with per-frame intrinsics or
masks), ``mask_path`` its image mask (ScanNet++'s DSLR frames have them).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .base import Camera
from .colmap import CameraList, colmap_camera
from .files import Src, read_mask

#: nerfstudio's perspective models (its ``CAMERA_MODEL_TO_TYPE``), read as OpenCV's pinhole.
PERSPECTIVE = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
MODELS = (*PERSPECTIVE, "OPENCV_FISHEYE", "EQUIRECTANGULAR")
#: What the frames may carry of their own.
_INTRINSICS = ("camera_model", "fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4",
               "p1", "p2", "camera_angle_x", "camera_angle_y", "is_fisheye")
#: ... and their image masks (zero: ignored), from the file's folder.
_OWN = (*_INTRINSICS, "mask_path")


def is_transforms(data) -> bool:
    """Whether a JSON document is a ``transforms.json``: ``frames``, and intrinsics at the
    top or in the frames."""
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        return False
    return any(k in data for k in _INTRINSICS) or any(
        isinstance(f, dict) and "fl_x" in f for f in data["frames"])


class TransformsCameras(CameraList):
    """The cameras of a ``transforms.json``: ``{None: fields}`` where every frame has the
    file's, else ``{file_path: fields}``, each frame's own over the file's."""

    def pick(self, key) -> Camera:
        keys = list(self)
        if keys == [None]:
            if key is not None:
                raise ValueError(f"{self.path}: every frame has the file's camera; leave the "
                                 f"key out (got {key!r})")
            return transforms_camera(Src(self.path), self[None])
        if key is None:
            raise ValueError(f"{self.path}: its frames have cameras of their own (intrinsics or "
                             f"masks; {len(keys)} "
                             f"frames, e.g. {keys[0]!r}); choose one by its file_path with key= "
                             "(--key on the command line), or list them with cameras.load_all "
                             "(usf-graph camera --all)")
        found = [k for k in keys if k is not None and Path(k) == Path(str(key))]  # ./ or not
        if not found:
            raise ValueError(f"{self.path}: no frame with file_path {key!r} (e.g. {keys[0]!r}); "
                             "choose one with key= (--key on the command line)")
        return transforms_camera(Src(self.path, found[0]), self[found[0]])


def read_transforms(path: Path, data: dict) -> TransformsCameras:
    """The cameras of the ``transforms.json`` ``path`` (``data``, its JSON)."""
    top = {k: data[k] for k in _INTRINSICS if k in data}
    frames = [f if isinstance(f, dict) else {} for f in data["frames"]]
    entries = {str(f.get("file_path", f"frame {i}")): {**top, **{k: f[k] for k in _OWN if k in f}}
               for i, f in enumerate(frames)}
    if len({repr(sorted(v.items())) for v in entries.values()}) <= 1:  # one camera for all
        entries = {None: next(iter(entries.values()), top)}
    return TransformsCameras(path, entries)


def transforms_camera(src: Src, f: dict) -> Camera:
    """One camera of a ``transforms.json`` from its fields (nerfstudio's names), with its
    frame's ``mask_path`` as its image mask; a focal length may be Instant-NGP's
    ``camera_angle_x`` (radians), the principal point its default, the image's centre."""
    cam = _intrinsics(src, f)
    if f.get("mask_path"):
        try:
            cam = cam.with_image_mask(read_mask(src.path.parent / str(f["mask_path"])))
        except ValueError as e:
            raise src.error(f"mask_path {f['mask_path']!r}: {e}") from None
    return cam


def _intrinsics(src: Src, f: dict) -> Camera:
    hint = "nerfstudio writes the image size as w and h"
    w, h = (src.pixels(src.finite(src.need(f, k, hint=hint), k), k)[0] for k in ("w", "h"))
    model = f.get("camera_model") or ("OPENCV_FISHEYE" if f.get("is_fisheye") else "OPENCV")
    if model not in MODELS:
        raise src.error(f"camera_model {model!r} is not read here (known: {', '.join(MODELS)}); "
                        "nerfstudio's stereo panoramas, VR180 and FISHEYE624 are not")
    if model == "EQUIRECTANGULAR":
        return colmap_camera(src, model, w, h, np.array([w, h], np.float64))
    fx = _focal(src, f, "x", w)
    fy = _focal(src, f, "y", h) if ("fl_y" in f or "camera_angle_y" in f) else fx
    cx, cy = (src.finite(f.get(k, size / 2), k) for k, size in (("cx", w), ("cy", h)))
    k1, k2, k3, k4, p1, p2 = (src.finite(f.get(k, 0.0), k) for k in ("k1", "k2", "k3", "k4", "p1", "p2"))
    if model == "OPENCV_FISHEYE":
        if p1 or p2:
            raise src.error(f"OPENCV_FISHEYE has no tangential terms, got p1={p1}, p2={p2}")
        return colmap_camera(src, model, w, h, np.array([fx, fy, cx, cy, k1, k2, k3, k4]))
    if k4:  # nerfstudio's perspective model: 1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8
        raise src.error(f"k4={k4}: the r^8 term of nerfstudio's perspective distortion has no "
                        "counterpart in OpenCV's model; recalibrate with k1 k2 k3 p1 p2")
    if k3:
        return colmap_camera(src, "FULL_OPENCV", w, h,
                             np.array([fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]))
    return colmap_camera(src, "OPENCV", w, h, np.array([fx, fy, cx, cy, k1, k2, p1, p2]))


def _focal(src: Src, f: dict, axis: str, size: int) -> float:
    """``fl_x``/``fl_y``, else from Instant-NGP's ``camera_angle_x``/``_y`` (the full field of
    view along that axis)."""
    if f"fl_{axis}" in f:
        return src.finite(f[f"fl_{axis}"], f"fl_{axis}")
    angle = src.finite(src.need(f, f"camera_angle_{axis}", hint=f"give fl_{axis} (pixels) or "
                                f"camera_angle_{axis} (radians)"), f"camera_angle_{axis}")
    if not 0 < angle < math.pi:
        raise src.error(f"camera_angle_{axis} must lie between 0 and pi radians, got {angle}")
    return 0.5 * size / math.tan(0.5 * angle)
