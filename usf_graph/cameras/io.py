"""Calibration files: Kalibr camchains, OpenCV FileStorage, ROS camera_info, OCamCalib,
and usf-graph's own YAML form."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from .base import FORMAT_TAG, Camera
from .fisheye import Fisheye, KannalaBrandt
from .omni import DoubleSphere, Mei
from .panorama import Equirectangular, LensNormalMap
from .pinhole import Pinhole
from .scaramuzza import Scaramuzza

MODELS = {c.__name__: c for c in (Pinhole, Fisheye, KannalaBrandt, Mei, DoubleSphere,
                                  Scaramuzza, Equirectangular)}


def _need(d: dict, key: str, path, where: str = ""):
    if not isinstance(d, dict) or key not in d:
        raise ValueError(f"{path}: missing key '{key}'{' in ' + where if where else ''}; "
                         "the calibration file is incomplete")
    return d[key]


def load(path, key: str | None = None) -> Camera:
    """Read a camera from a calibration file; the format is detected from the content.

    Supported: Kalibr camchain YAML (``key`` picks the camera, ``cam0`` by default),
    OpenCV FileStorage YAML/XML, ROS camera_info YAML, OCamCalib ``calib_results.txt``,
    lens normal maps (``.npy``/``.npz``) and usf-graph's own YAML (:meth:`Camera.save`).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"calibration file {path} does not exist")
    if path.suffix in (".npy", ".npz"):
        return LensNormalMap.from_file(path)
    text = path.read_text(errors="replace")
    head = text.lstrip()[:64]
    if path.suffix == ".xml" or head.startswith("%YAML") or head.startswith("<?xml"):
        return _load_opencv(path)
    if "polynomial coefficients" in text or path.name.startswith("calib_results"):
        return _load_ocamcalib(path, text)
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise ValueError(f"{path}: not valid YAML ({e})") from e
    if not isinstance(data, dict):
        raise ValueError(f"{path}: unrecognized calibration file (expected a YAML mapping)")
    if FORMAT_TAG in data:
        return _load_own(path, data)
    if any(isinstance(v, dict) and "camera_model" in v for v in data.values()):
        return _load_kalibr(path, data, key or "cam0")
    if "camera_matrix" in data:
        return _load_ros(path, data)
    raise ValueError(f"{path}: unrecognized calibration format; expected Kalibr camchain, "
                     "ROS camera_info, OpenCV FileStorage, OCamCalib or usf-graph YAML")


def save(cam: Camera, path) -> None:
    """Write ``cam`` in usf-graph's YAML form, atomically (:meth:`Camera.save`)."""
    cam.save(path)


def _load_own(path, data) -> Camera:
    name = _need(data, "model", path)
    if name not in MODELS:
        raise ValueError(f"{path}: unknown camera model '{name}'; known: {sorted(MODELS)}")
    return MODELS[name](**_need(data, "params", path), rotation=data.get("rotation"))


def _k_from_matrix(K, path):
    K = np.asarray(K, np.float64).reshape(3, 3)
    return K[0, 0], K[1, 1], K[0, 2], K[1, 2]


def _load_kalibr(path, data, key) -> Camera:
    if key not in data:
        raise ValueError(f"{path}: no camera '{key}' in the camchain (has {list(data)}); pass key=")
    c = data[key]
    model = _need(c, "camera_model", path, key)
    intr = [float(v) for v in _need(c, "intrinsics", path, key)]
    dm = c.get("distortion_model", "none")
    dist = [float(v) for v in c.get("distortion_coeffs", []) or []]
    w, h = (int(v) for v in _need(c, "resolution", path, key))
    if model == "pinhole":
        fx, fy, cx, cy = intr
        if dm == "radtan":
            return Pinhole(fx, fy, cx, cy, w, h, dist=dist)
        if dm == "equidistant":
            return KannalaBrandt(fx, fy, cx, cy, w, h, k=dist)
        if dm == "none":
            return Pinhole(fx, fy, cx, cy, w, h)
    elif model == "omni":
        xi, fx, fy, cx, cy = intr
        if dm in ("radtan", "none"):
            return Mei(fx, fy, cx, cy, w, h, xi=xi, dist=dist if dm == "radtan" else (0, 0, 0, 0))
    elif model == "ds":
        xi, alpha, fx, fy, cx, cy = intr
        if dm == "none":
            return DoubleSphere(fx, fy, cx, cy, w, h, xi=xi, alpha=alpha)
    else:
        raise ValueError(f"{path}: unknown Kalibr camera_model '{model}' in {key}; "
                         "supported: pinhole, omni, ds")
    raise ValueError(f"{path}: Kalibr {model}-{dm} is not supported; supported: pinhole-radtan, "
                     "pinhole-equidistant, pinhole-none, omni-radtan, omni-none, ds-none")


def _load_ros(path, data) -> Camera:
    K = _need(_need(data, "camera_matrix", path), "data", path, "camera_matrix")
    fx, fy, cx, cy = _k_from_matrix(K, path)
    w, h = int(_need(data, "image_width", path)), int(_need(data, "image_height", path))
    dm = _need(data, "distortion_model", path)
    D = [float(v) for v in _need(_need(data, "distortion_coefficients", path), "data", path,
                                 "distortion_coefficients")]
    if dm in ("plumb_bob", "rational_polynomial"):
        return Pinhole(fx, fy, cx, cy, w, h, dist=D or None)
    if dm == "equidistant":
        return KannalaBrandt(fx, fy, cx, cy, w, h, k=D[:4])
    raise ValueError(f"{path}: unknown ROS distortion_model '{dm}'; supported: plumb_bob, "
                     "rational_polynomial, equidistant")


def _load_opencv(path) -> Camera:
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as e:
        raise ValueError(f"{path}: OpenCV cannot parse this FileStorage file ({e})") from e
    if not fs.isOpened():
        raise ValueError(f"{path}: OpenCV cannot open this FileStorage file")
    try:
        def node(name):
            n = fs.getNode(name)
            if n.empty():
                raise ValueError(f"{path}: missing key '{name}'; the calibration file is incomplete")
            return n

        K = node("camera_matrix").mat()
        D = node("distortion_coefficients").mat()
        w, h = int(node("image_width").real()), int(node("image_height").real())
        model = fs.getNode("distortion_model")
        model = model.string() if not model.empty() else "pinhole"
        xi = fs.getNode("xi")
    finally:
        fs.release()
    if K is None or K.size != 9:
        raise ValueError(f"{path}: camera_matrix must be a 3x3 !!opencv-matrix")
    fx, fy, cx, cy = _k_from_matrix(K, path)
    D = [] if D is None else D.ravel().tolist()
    if not xi.empty():
        return Mei(fx, fy, cx, cy, w, h, xi=xi.real(), dist=D[:4])
    if model in ("fisheye", "equidistant", "kannala-brandt"):
        return KannalaBrandt(fx, fy, cx, cy, w, h, k=D[:4])
    if model not in ("pinhole", "plumb_bob", "rational_polynomial", "radtan"):
        raise ValueError(f"{path}: unknown distortion_model '{model}'; supported: pinhole, fisheye")
    return Pinhole(fx, fy, cx, cy, w, h, dist=D or None)


def _load_ocamcalib(path, text) -> Camera:
    rows = [ln.strip() for ln in text.splitlines()]
    nums = [ln for ln in rows if ln and not ln.startswith("#")]
    try:
        vals = [[float(t) for t in ln.split()] for ln in nums]
        pol, invpol, center, affine, size = vals[0], vals[1], vals[2], vals[3], vals[4]
        if int(pol[0]) != len(pol) - 1 or int(invpol[0]) != len(invpol) - 1:
            raise ValueError("the coefficient counts do not match the listed coefficients")
        if len(center) != 2 or len(affine) != 3 or len(size) != 2:
            raise ValueError("expected 'row col' centre, 'c d e' affine and 'height width'")
    except (ValueError, IndexError) as e:
        raise ValueError(f"{path}: malformed OCamCalib calib_results.txt ({e}); expected the "
                         "sections pol, invpol, centre, affine, size") from e
    h, w = int(size[0]), int(size[1])
    return Scaramuzza(pol[1:], center, affine, w, h, invpol=invpol[1:])
