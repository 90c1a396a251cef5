"""Calibration files: every common format is read into one dict, then recognized by its keys.

Formats (detected from the content, not the file name):

- Kalibr camchain YAML: ``cam0``, ``cam1``, ... with ``camera_model`` pinhole | omni | ds |
  eucm and ``distortion_model`` radtan | equidistant | none; the extrinsics
  ``T_cn_cnm1``/``T_cam_imu`` place each camera in the rig.
- OpenCV FileStorage YAML/XML (``%YAML:1.0``, ``%YAML 1.2``, ``<opencv_storage>``):
  ``camera_matrix``, ``distortion_coefficients``, ``image_width``, ``image_height``; a
  fisheye when ``fisheye_model: 1`` (OpenCV's calibration sample) or ``distortion_model:
  fisheye``; Mei when there is an ``xi`` (``cv2.omnidir``, a 1x1 matrix or a number).
- ``K``/``D``/``DIM`` (the common ``cv2.fisheye`` scripts), as YAML, FileStorage or ``.npz``:
  Kannala-Brandt when ``D`` has 4 coefficients, else OpenCV's pinhole distortion.
- ROS ``camera_info`` YAML: plumb_bob | rational_polynomial | equidistant.
- The USF reference code's sensor YAML: ``image_width``, ``image_height``,
  ``intrinsic.model_type`` (0 pinhole, 1 Mei), ``intrinsic.mirror_parameters.xi``,
  ``intrinsic.distortion_parameters`` (k1 k2 p1 p2), ``intrinsic.projection_parameters``
  (fx fy cx cy, or gamma1 gamma2 u0 v0), optional ``mask`` (image) and ``lens_normal_map``
  (``.npy``), paths relative to the file. CamOdoCal's flat form (``model_type: MEI``) too.
- OCamCalib ``calib_results.txt``; lens normal maps ``.npy``/``.npz`` (``rays``, ``valid``).
- usf-graph's own YAML (:meth:`Camera.save`), with optional ``fov_deg`` and ``image_mask``.

Every error names the file, the key and what would be accepted.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from .base import DEFAULT_ROTATION, FORMAT_TAG, Camera, check_rotation, plain
from .fisheye import Fisheye, KannalaBrandt
from .omni import EUCM, DoubleSphere, Mei
from .panorama import Equirectangular, LensNormalMap
from .pinhole import Pinhole
from .scaramuzza import Scaramuzza

MODELS = {c.__name__: c for c in (Pinhole, Fisheye, KannalaBrandt, Mei, DoubleSphere, EUCM,
                                  Scaramuzza, Equirectangular)}
FORMATS = ("Kalibr camchain", "OpenCV FileStorage (pinhole, fisheye_model, cv2.omnidir xi)",
           "K/D/DIM (cv2.fisheye scripts)", "ROS camera_info", "USF sensor YAML",
           "OCamCalib calib_results.txt", "lens normal map .npy/.npz", "usf-graph YAML")

# Kalibr's intrinsics per camera_model, and the (model, distortion) pairs we read.
_KALIBR_INTRINSICS = {"pinhole": "fu fv pu pv", "omni": "xi fu fv pu pv",
                      "ds": "xi alpha fu fv pu pv", "eucm": "alpha beta fu fv pu pv"}
_KALIBR_DIST = {"radtan": 4, "equidistant": 4, "none": 0}
_KALIBR_PAIRS = ("pinhole-radtan", "pinhole-equidistant", "pinhole-none", "omni-radtan",
                 "omni-none", "ds-none", "eucm-none")
_PINHOLE_DIST = ("plumb_bob", "rational_polynomial", "pinhole", "radtan")
_FISHEYE_DIST = ("equidistant", "fisheye", "kannala-brandt", "kb4")


class _Src:
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
                             f"{_plain_list(a)}")
        return a

    def build(self, cls, **kw) -> Camera:
        try:
            return cls(**kw)
        except ValueError as e:
            raise self.error(str(e)) from None


def load(path, key: str | None = None, fov_deg: float | None = None, image_mask=None) -> Camera:
    """Read a camera from a calibration file in any of the formats of this module.

    Args:
        path: the file.
        key: the camera in a Kalibr camchain (``cam0`` by default; ``--key`` on the
            command line). An error for files that hold one camera.
        fov_deg: optional usable field of view (:meth:`Camera.with_fov`), over the file's.
        image_mask: optional ``[H, W]`` mask or image file, over the file's.

    A camera of a Kalibr chain comes back mounted in the rig: its ``rotation`` is the
    rotation from its optical frame to the rig's sphere frame, which is cam0's (cam0 looks
    along +x). See :func:`load_rig` for all of them at once.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"calibration file {path} does not exist")
    data = _read(path)
    if isinstance(data, Camera):
        fmt, cam = ("OCamCalib" if isinstance(data, Scaramuzza) else "lens normal map"), data
    elif _is_kalibr(data):
        names = _kalibr_names(data)
        key = key or names[0]
        if key not in data:
            raise ValueError(f"{path}: no camera '{key}' in the camchain (it has {names}); "
                             "choose one with key= (--key on the command line)")
        cam = _load_kalibr(_Src(path, key), data[key])
        rot = _kalibr_rotation(path, data, key)
        cam, fmt = cam.with_rotation(DEFAULT_ROTATION @ rot if rot is not None else None), None
    else:
        fmt, cam = _load_single(path, data)
    if key is not None and fmt is not None:
        raise ValueError(f"{path}: key={key!r} (--key) picks a camera in a Kalibr camchain, but "
                         f"this is {'an' if fmt[0] in 'AEIOU' else 'a'} {fmt} file with one camera; leave "
                         "the key out")
    if fov_deg is not None:
        cam = cam.with_fov(fov_deg)
    if image_mask is not None:
        cam = cam.with_image_mask(read_mask(image_mask) if isinstance(image_mask, (str, Path))
                                  else image_mask)
    return cam


def load_rig(path) -> dict[str, Camera]:
    """All cameras of a Kalibr camchain, each mounted in the rig (cam0's frame, looking
    along +x), in the file's order. Every camera after the first needs ``T_cn_cnm1`` (or
    each a ``T_cam_imu``). Translations are ignored: the rig is treated as one centre of
    projection, which holds for scenes far away compared to the baseline."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"calibration file {path} does not exist")
    data = _read(path)
    if isinstance(data, Camera) or not _is_kalibr(data):
        raise ValueError(f"{path}: a rig is read from a Kalibr camchain (cam0, cam1, ... with "
                         "T_cn_cnm1); this file holds one camera, use cameras.load")
    rig = {}
    for name in _kalibr_names(data):
        rot = _kalibr_rotation(path, data, name)
        if rot is None:
            raise ValueError(f"{path} [{name}]: no 'T_cn_cnm1' (or 'T_cam_imu' on it and on "
                             f"cam0), so its place in the rig is unknown; add the extrinsics")
        rig[name] = _load_kalibr(_Src(path, name), data[name]).with_rotation(DEFAULT_ROTATION @ rot)
    return rig


def save(cam: Camera, path) -> None:
    """Write ``cam`` in usf-graph's YAML form, atomically (:meth:`Camera.save`)."""
    cam.save(path)


def read_mask(path) -> np.ndarray:
    """An image mask from an image file: nonzero pixels are seen, zero ones ignored."""
    import cv2

    m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if m is None:
        raise ValueError(f"cannot read the image mask {path}: not an image file OpenCV reads")
    return (m if m.ndim == 2 else m.max(-1)) != 0


# -- reading any file into a dict ----------------------------------------------------------

def _read(path: Path):
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
    if path.suffix == ".xml" or head.startswith(("%YAML", "<?xml", "<opencv_storage")) \
            or "opencv-matrix" in text:
        return _read_filestorage(path)
    if "polynomial coefficients" in text or path.name.startswith("calib_results"):
        return _load_ocamcalib(path, text)
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
    except cv2.error as e:
        raise ValueError(f"{path}: OpenCV cannot parse this FileStorage file ({e})") from e
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


# -- single-camera formats -----------------------------------------------------------------

def _plain_list(a) -> str:
    return "[" + ", ".join(plain(x) for x in np.ravel(a)) + "]"


def _load_single(path: Path, data: dict):
    """(format name, camera) for every format that holds one camera."""
    src = _Src(path)
    if FORMAT_TAG in data:
        return "usf-graph", _load_own(src, data)
    if "intrinsic" in data or ("model_type" in data and "projection_parameters" in data):
        return "USF sensor", _load_usf(src, data)
    if "camera_matrix" in data:
        ros = isinstance(data["camera_matrix"], dict)
        return ("ROS camera_info" if ros else "OpenCV"), _load_opencv(src, data, ros)
    if "K" in data:
        return "K/D/DIM", _load_kdd(src, data)
    raise ValueError(f"{path}: unrecognized calibration format (top-level keys: "
                     f"{sorted(map(str, data))}); readable formats: {', '.join(FORMATS)}")


def _size(src: _Src, data: dict) -> tuple[int, int]:
    hint = "give the image size as image_width and image_height"
    w, h = (src.number(src.need(data, k, hint=hint), k) for k in ("image_width", "image_height"))
    return int(w), int(h)


def _k(src: _Src, K, name: str):
    K = src.array(K, name, (9,)).reshape(3, 3)
    return dict(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2])


def from_doc(doc: dict) -> Camera:
    """A camera from :meth:`Camera.to_doc`'s plain data."""
    return _load_own(_Src(Path("<camera document>")), doc)


def _load_own(src: _Src, data: dict) -> Camera:
    name = src.need(data, "model")
    if name not in MODELS:
        raise src.error(f"unknown camera model '{name}'; known: {sorted(MODELS)}")
    try:
        cam = MODELS[name](**src.need(data, "params"), rotation=data.get("rotation"))
    except (TypeError, ValueError) as e:
        raise src.error(f"bad parameters for {name} ({e})") from None
    return _extras(src, cam, data.get("fov_deg"), data.get("image_mask"))


def _extras(src: _Src, cam: Camera, fov, mask) -> Camera:
    try:
        if fov is not None:
            cam = cam.with_fov(src.number(fov, "fov_deg"))
        if mask is not None:
            cam = cam.with_image_mask(read_mask(src.path.parent / mask))
    except ValueError as e:
        raise src.error(str(e)) from None
    return cam


def _load_opencv(src: _Src, data: dict, ros: bool) -> Camera:
    K = _k(src, data["camera_matrix"], "camera_matrix")
    w, h = _size(src, data)
    D = src.array(src.need(data, "distortion_coefficients"), "distortion_coefficients")
    if "xi" in data:  # cv2.omnidir: Mei, whose K[0, 1] is a skew the model uses
        skew = float(src.array(data["camera_matrix"], "camera_matrix")[1])
        return src.build(Mei, **K, width=w, height=h, xi=src.number(data["xi"], "xi"),
                         dist=_pad(src, D, 4, "distortion_coefficients"), skew=skew)
    model = data.get("distortion_model")
    if model is None:
        if ros:
            src.need(data, "distortion_model",
                     hint=f"ROS camera_info needs one of {_PINHOLE_DIST[:2] + ('equidistant',)}")
        model = "fisheye" if data.get("fisheye_model") else "pinhole"
    model = str(model).lower()
    if model in _FISHEYE_DIST:
        return src.build(KannalaBrandt, **K, width=w, height=h,
                         k=_pad(src, D, 4, "distortion_coefficients"))
    if model in _PINHOLE_DIST:
        return src.build(Pinhole, **K, width=w, height=h, dist=D if D.size else None)
    kind = "ROS" if ros else "OpenCV"
    raise src.error(f"unknown {kind} distortion_model '{model}'; supported: "
                    f"{', '.join(_PINHOLE_DIST + _FISHEYE_DIST)}")


def _pad(src: _Src, D: np.ndarray, n: int, name: str) -> np.ndarray:
    """The first ``n`` coefficients; extra ones must be zero (OpenCV pads to 5 or 8)."""
    if D.size < n and D.size != 0:
        raise src.error(f"'{name}' must have {n} coefficients, got {D.size}")
    if np.any(D[n:] != 0):
        raise src.error(f"'{name}' has {D.size} coefficients but this model uses {n}; "
                        f"the extra ones are not zero: {_plain_list(D[n:])}")
    return np.pad(D[:n], (0, n - min(n, D.size)))


def _load_kdd(src: _Src, data: dict) -> Camera:
    K = _k(src, data["K"], "K")
    D = src.array(src.need(data, "D", hint="K/D/DIM files need the distortion D"), "D",
                  (4, 5, 8, 12))
    if "DIM" in data:
        w, h = (int(v) for v in src.array(data["DIM"], "DIM", (2,)))
    else:
        w, h = _size(src, data) if "image_width" in data else (None, None)
        if w is None:
            src.need(data, "DIM", hint="give the image size as DIM: [width, height]")
    model = str(data.get("distortion_model", "fisheye" if D.size == 4 else "pinhole")).lower()
    if model in _FISHEYE_DIST:
        return src.build(KannalaBrandt, **K, width=w, height=h, k=_pad(src, D, 4, "D"))
    if model in _PINHOLE_DIST:
        return src.build(Pinhole, **K, width=w, height=h, dist=D if D.size else None)
    raise src.error(f"unknown distortion_model '{model}'; supported: "
                    f"{', '.join(_PINHOLE_DIST + _FISHEYE_DIST)}")


_USF_MODELS = {0: "pinhole", 1: "mei", "pinhole": "pinhole", "mei": "mei"}


def _load_usf(src: _Src, data: dict) -> Camera:
    w, h = _size(src, data)
    intr = data.get("intrinsic", data)
    where = "intrinsic" if "intrinsic" in data else ""
    mt = src.need(intr, "model_type", where)
    model = _USF_MODELS.get(mt.lower() if isinstance(mt, str) else mt)
    if model is None:
        raise src.error(f"unknown model_type {mt!r}; supported: 0 (pinhole), 1 (Mei)")
    dp = intr.get("distortion_parameters") or {}
    dist = [src.number(src.need(dp, k, "distortion_parameters"), k) for k in ("k1", "k2", "p1", "p2")] \
        if dp else [0.0] * 4
    pp = src.need(intr, "projection_parameters", where)
    names = ("fx", "fy", "cx", "cy") if model == "pinhole" else ("gamma1", "gamma2", "u0", "v0")
    f = [src.number(src.need(pp, k, "projection_parameters"), k) for k in names]
    K = dict(zip(("fx", "fy", "cx", "cy"), f))
    if model == "pinhole":
        cam = src.build(Pinhole, **K, width=w, height=h, dist=dist)
    else:
        mp = src.need(intr, "mirror_parameters", where)
        cam = src.build(Mei, **K, width=w, height=h, xi=src.number(src.need(mp, "xi"), "xi"),
                        dist=dist)
    if data.get("lens_normal_map"):
        lnm = LensNormalMap.from_file(src.path.parent / data["lens_normal_map"])
        if (lnm.width, lnm.height) != (w, h):
            raise src.error(f"lens_normal_map is {lnm.width} x {lnm.height} but the image is "
                            f"{w} x {h} (width x height)")
        cam = lnm  # a measured ray table beats the fitted model
    return _extras(src, cam, data.get("fov_deg"), data.get("mask"))


# -- Kalibr ------------------------------------------------------------------------------

def _is_kalibr(data: dict) -> bool:
    return any(isinstance(v, dict) and "camera_model" in v for v in data.values())


def _kalibr_names(data: dict) -> list[str]:
    return [k for k, v in data.items() if isinstance(v, dict) and "camera_model" in v]


def _load_kalibr(src: _Src, c: dict) -> Camera:
    model = src.need(c, "camera_model")
    if model not in _KALIBR_INTRINSICS:
        raise src.error(f"unknown Kalibr camera_model '{model}'; supported: "
                        f"{', '.join(_KALIBR_INTRINSICS)}")
    names = _KALIBR_INTRINSICS[model].split()
    intr = src.array(src.need(c, "intrinsics"), "intrinsics")
    if intr.size != len(names):
        raise src.error(f"Kalibr '{model}' intrinsics are [{', '.join(names)}] ({len(names)} "
                        f"values), got {intr.size}: {_plain_list(intr)}")
    p = dict(zip(names, intr.tolist()))
    dm = c.get("distortion_model", "none")
    if f"{model}-{dm}" not in _KALIBR_PAIRS:
        raise src.error(f"Kalibr {model}-{dm} is not supported; supported: {', '.join(_KALIBR_PAIRS)}")
    dist = src.array(c.get("distortion_coeffs") or [], "distortion_coeffs")
    if dist.size != _KALIBR_DIST[dm]:
        raise src.error(f"Kalibr distortion_model '{dm}' takes {_KALIBR_DIST[dm]} "
                        f"distortion_coeffs, got {dist.size}")
    w, h = (int(v) for v in src.array(src.need(c, "resolution"), "resolution", (2,)))
    K = dict(fx=p["fu"], fy=p["fv"], cx=p["pu"], cy=p["pv"], width=w, height=h)
    if model == "pinhole":
        if dm == "equidistant":
            return src.build(KannalaBrandt, **K, k=dist)
        return src.build(Pinhole, **K, dist=dist if dist.size else None)
    if model == "omni":
        return src.build(Mei, **K, xi=p["xi"], dist=dist if dist.size else (0, 0, 0, 0))
    if model == "ds":
        return src.build(DoubleSphere, **K, xi=p["xi"], alpha=p["alpha"])
    return src.build(EUCM, **K, alpha=p["alpha"], beta=p["beta"])


def _transform_rotation(path, name: str, key: str, T) -> np.ndarray:
    src = _Src(path, name)
    T = src.array(T, key, (12, 16))
    try:
        return check_rotation(T.reshape(-1, 4)[:3, :3])
    except ValueError as e:
        raise src.error(f"'{key}' is not a rigid transform ({e})") from None


def _kalibr_rotation(path, data: dict, key: str) -> np.ndarray | None:
    """Rotation from ``key``'s optical frame to cam0's, from the T_cn_cnm1 chain (or both
    cameras' T_cam_imu); None when the file does not say."""
    names = _kalibr_names(data)
    idx = names.index(key)
    R = np.eye(3)
    for name in names[1:idx + 1]:
        T = data[name].get("T_cn_cnm1")
        if T is None:
            break
        R = R @ _transform_rotation(path, name, "T_cn_cnm1", T).T  # R_c0<-cn
    else:
        return R
    t0, tk = data[names[0]].get("T_cam_imu"), data[key].get("T_cam_imu")
    if t0 is None or tk is None:
        return None
    return _transform_rotation(path, names[0], "T_cam_imu", t0) @ \
        _transform_rotation(path, key, "T_cam_imu", tk).T


# -- OCamCalib -----------------------------------------------------------------------------

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
    return _Src(Path(path)).build(Scaramuzza, pol=pol[1:], center=center, affine=affine,
                                  width=w, height=h, invpol=invpol[1:])

