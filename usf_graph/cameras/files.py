"""Reading calibration files: any format into one dict, and the context errors name (the
file and the camera in it)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import yaml

from .base import Camera, check_finite, check_rotation, mask_from_image, plain
from .panorama import LensNormalMap

FORMATS = ("Kalibr camchain", "OpenCV FileStorage (pinhole, fisheye_model, cv2.omnidir xi)",
           "K/D/DIM (cv2.fisheye scripts)", "ROS camera_info",
           "USF sensor or CamOdoCal/VINS-Fusion YAML",
           "OCamCalib calib_results.txt", "lens normal map .npy/.npz", "usf-graph YAML",
           "COLMAP cameras.txt/cameras.bin or a sparse model's folder", "Basalt calibration JSON",
           "ORB-SLAM3 settings", "nerfstudio/Instant-NGP transforms.json",
           "WoodScape calibration JSON")


class Src:
    """Where a value came from, for error messages: the file and the camera in it."""

    def __init__(self, path: Path, key: str | None = None):
        self.path, self.key = path, key

    def __str__(self) -> str:
        return f"{self.path}" + (f" [{self.key}]" if self.key else "")

    def error(self, msg: str) -> ValueError:
        return ValueError(f"{self}: {msg}")

    def need(self, d, name: str, where: str = "", hint: str = ""):
        if not isinstance(d, dict) or name not in d or d[name] is None:
            inside = f" in '{where}'" if where else ""
            raise self.error(f"missing key '{name}'{inside}; {hint or 'the calibration file is incomplete'}")
        return d[name]

    def number(self, v, name: str) -> float:
        a = np.asarray(v, dtype=object if isinstance(v, dict) else None)
        if a.dtype == object or a.size != 1:
            raise self.error(f"'{name}' must be one number, got {v!r}")
        try:
            return float(a.reshape(()))
        except (TypeError, ValueError):
            raise self.error(f"'{name}' must be a number, got {v!r}") from None

    def finite(self, v, name: str) -> float:
        """:meth:`number`, refusing NaN and infinities."""
        x = self.number(v, name)
        if not np.isfinite(x):
            raise self.error(f"'{name}' must be finite, got {x}")
        return x

    def pixels(self, v, name: str) -> tuple[int, ...]:
        """Image sizes in pixels: whole positive numbers. A file's 752.7 is refused, not
        truncated to 752."""
        a = np.atleast_1d(np.asarray(v, np.float64))
        if not (np.isfinite(a).all() and (a == np.round(a)).all() and (a >= 1).all()):
            raise self.error(f"'{name}' must be whole positive numbers of pixels, got "
                             f"{plain_list(a)}")
        return tuple(int(x) for x in a)

    def array(self, v, name: str, sizes: tuple = ()) -> np.ndarray:
        """A matrix or vector given as an OpenCV matrix, a ROS ``{rows, cols, data}`` map or
        a (nested) list; ``sizes``: the accepted numbers of elements."""
        if isinstance(v, dict):
            v = self.need(v, "data", name)
        try:
            a = np.asarray(v, np.float64).ravel()
        except (TypeError, ValueError):
            raise self.error(f"'{name}' must hold numbers, got {v!r}") from None
        if sizes and a.size not in sizes:
            want = " or ".join(str(s) for s in sizes)
            raise self.error(f"'{name}' must have {want} elements, got {a.size}: "
                             f"{plain_list(a)}")
        return a

    def rigid(self, v, name: str) -> np.ndarray:
        """A rigid transform ``[4, 4]`` given as 12 or 16 numbers, row by row (its last row,
        if given, is ignored)."""
        T = self.array(v, name, (12, 16)).reshape(-1, 4)
        return self.pose(T[:3, :3], T[:3, 3], name)

    def pose(self, R, t, name: str) -> np.ndarray:
        """``[4, 4]`` from a rotation and a translation, both checked."""
        try:
            R = check_rotation(R)
            t = check_finite(name, np.asarray(t, np.float64))
        except ValueError as e:
            raise self.error(f"'{name}' is not a rigid transform ({e})") from None
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        return T

    def build(self, cls, **kw) -> Camera:
        try:
            return cls(**kw)
        except ValueError as e:
            raise self.error(str(e)) from None


def plain_list(a) -> str:
    return "[" + ", ".join(plain(x) for x in np.ravel(a)) + "]"


def read_mask(path) -> np.ndarray:
    """An image mask from an image file: nonzero pixels are seen, zero ones ignored."""
    from ..fileio import decode_image

    if not Path(path).is_file():
        raise ValueError(f"cannot read the image mask {path}: it does not exist")
    m = decode_image(path)
    if m is None:
        raise ValueError(f"cannot read the image mask {path}: not an image file OpenCV reads")
    return mask_from_image(m)


def read_document(path: Path, ocamcalib):
    """A calibration file as a dict (YAML, OpenCV FileStorage, ``.npz`` with K and D), or
    as a camera for the files that are one (lens normal maps, OCamCalib via ``ocamcalib``)."""
    if path.suffix == ".npy":
        return LensNormalMap.from_file(path)
    if path.suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                keys = set(z.files)
                if "rays" not in keys and {"K", "D"} <= keys:
                    return {k: z[k] for k in z.files}
        except Exception as e:  # noqa: BLE001 - numpy raises many kinds here
            raise ValueError(f"cannot read {path}: {e}") from e
        return LensNormalMap.from_file(path)
    text = path.read_text(errors="replace")
    head = text.lstrip()[:64]
    if head.startswith("{"):  # JSON (Basalt); YAML 1.1 would read 1e-05 as a string
        try:
            return json.loads(text)
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}: not valid JSON ({e})") from e
    if path.suffix == ".xml" or head.startswith(("%YAML", "<?xml", "<opencv_storage")) \
            or "opencv-matrix" in text:
        return _read_filestorage(path)
    if "polynomial coefficients" in text or path.name.startswith("calib_results"):
        return ocamcalib(path, text)
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise ValueError(f"{path}: not valid YAML ({e})") from e
    if not isinstance(data, dict):
        raise ValueError(f"{path}: unrecognized calibration file (expected a YAML mapping); "
                         f"readable formats: {', '.join(FORMATS)}")
    return data


def _read_filestorage(path: Path) -> dict:
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as e:  # OpenCV 5's binding wraps its parse error in SystemError
        why = str(e.__cause__ if isinstance(e.__cause__, cv2.error) else e).strip()
        raise ValueError(f"{path}: OpenCV cannot parse this FileStorage file ({why})") from e
    if not fs.isOpened():
        raise ValueError(f"{path}: OpenCV cannot open this FileStorage file")
    try:
        return _node(fs.root())
    except cv2.error as e:
        raise ValueError(f"{path}: OpenCV cannot read a node of this file ({e})") from e
    finally:
        fs.release()


def _node(n):
    if n.isMap():
        keys = n.keys()
        if {"rows", "cols", "dt", "data"} <= set(keys):  # an !!opencv-matrix
            return np.asarray(n.mat(), np.float64)
        return {k: _node(n.getNode(k)) for k in keys}
    if n.isSeq():
        return [_node(n.at(i)) for i in range(n.size())]
    if n.isInt():
        return int(n.real())
    if n.isReal():
        return float(n.real())
    if n.isString():
        return n.string()
    return None
