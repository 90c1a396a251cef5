"""The calibration formats that hold one camera: usf-graph's own YAML, OpenCV
FileStorage and ROS ``camera_info``, ``K``/``D``/``DIM``, the USF sensor and CamOdoCal YAML and
OCamCalib (:mod:`.io` recognizes a file's format and reads rigs)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .base import FORMAT_TAG, Camera
from .cubemap import Cubemap, EquiAngularCubemap
from .files import FORMATS, Src, plain_list, read_mask
from .fisheye import FOV, Fisheye, KannalaBrandt, RadialPoly
from .omni import EUCM, DoubleSphere, Mei
from .panorama import Equirectangular, LensNormalMap
from .pinhole import Division, Pinhole
from .scaramuzza import Scaramuzza
from .woodscape import is_woodscape, load_woodscape

MODELS = {c.__name__: c for c in (Pinhole, Division, Fisheye, KannalaBrandt, FOV, Mei,
                                  DoubleSphere, EUCM, Scaramuzza, Equirectangular, Cubemap,
                                  EquiAngularCubemap, RadialPoly)}
_PINHOLE_DIST = ("plumb_bob", "rational_polynomial", "pinhole", "radtan")
_FISHEYE_DIST = ("equidistant", "fisheye", "kannala-brandt", "kb4")


def with_fov_and_mask(cam: Camera, fov_deg: float | None = None, image_mask=None) -> Camera:
    """``cam`` with a usable field of view (:meth:`Camera.with_fov`) and an image mask
    (``[H, W]`` array, or an image file: :func:`read_mask`), each where given."""
    if fov_deg is not None:
        cam = cam.with_fov(fov_deg)
    if image_mask is not None:
        cam = cam.with_image_mask(read_mask(image_mask) if isinstance(image_mask, (str, Path))
                                  else image_mask)
    return cam


def _load_single(path: Path, data: dict):
    """(format name, camera) for every format that holds one camera."""
    src = Src(path)
    if FORMAT_TAG in data:
        return "usf-graph", _load_own(src, data)
    if is_woodscape(data):
        return "WoodScape", load_woodscape(src, data)
    if "intrinsic" in data or ("model_type" in data and "projection_parameters" in data):
        return "USF sensor", _load_usf(src, data)
    if "camera_matrix" in data:
        ros = isinstance(data["camera_matrix"], dict)
        return ("ROS camera_info" if ros else "OpenCV"), _load_opencv(src, data, ros)
    if "K" in data:
        return "K/D/DIM", _load_kdd(src, data)
    raise ValueError(f"{path}: unrecognized calibration format (top-level keys: "
                     f"{sorted(map(str, data))}); readable formats: {', '.join(FORMATS)}")


def _size(src: Src, data: dict) -> tuple[int, int]:
    hint = "give the image size as image_width and image_height"
    w, h = (src.pixels(src.number(src.need(data, k, hint=hint), k), k)[0]
            for k in ("image_width", "image_height"))
    return w, h


def _k(src: Src, K, name: str):
    K = src.array(K, name, (9,)).reshape(3, 3)
    return dict(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2])


def camera_info_to_camera(data: dict, path, key: str) -> Camera:
    """A camera from a ROS ``camera_info`` as a dict (``image_width``, ``image_height``,
    ``camera_matrix``, ``distortion_model``, ``distortion_coefficients``), e.g. a bag's
    message; errors name ``path [key]``."""
    src = Src(Path(str(path)), key)
    if not np.any(src.array(src.need(data, "camera_matrix"), "camera_matrix")):
        raise src.error("the camera_info is uncalibrated (K is all zeros); calibrate the camera "
                        "or give its calibration file with --camera")
    return _load_opencv(src, data, ros=True)


def from_doc(doc: dict) -> Camera:
    """A camera from :meth:`Camera.to_doc`'s plain data."""
    return _load_own(Src(Path("<camera document>")), doc)


def _load_own(src: Src, data: dict) -> Camera:
    name = src.need(data, "model")
    if name not in MODELS:
        raise src.error(f"unknown camera model '{name}'; known: {sorted(MODELS)}")
    try:
        cam = MODELS[name](**src.need(data, "params"), rotation=data.get("rotation"))
    except (TypeError, ValueError) as e:
        raise src.error(f"bad parameters for {name} ({e})") from None
    cam = _extras(src, cam, data.get("fov_deg"), data.get("image_mask"))
    try:
        if data.get("position") is not None:
            cam = cam.with_position(data["position"])
        return cam.with_distance(data.get("distance"))
    except ValueError as e:
        raise src.error(str(e)) from None


def _extras(src: Src, cam: Camera, fov, mask) -> Camera:
    try:
        return with_fov_and_mask(cam, None if fov is None else src.number(fov, "fov_deg"),
                                 None if mask is None else src.path.parent / mask)
    except ValueError as e:
        raise src.error(str(e)) from None


def _load_opencv(src: Src, data: dict, ros: bool) -> Camera:
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
                     hint=f"ROS camera_info needs one of {', '.join(_PINHOLE_DIST[:2] + ('equidistant',))}")
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


def _pad(src: Src, D: np.ndarray, n: int, name: str) -> np.ndarray:
    """The first ``n`` coefficients; extra ones must be zero (OpenCV pads to 5 or 8)."""
    if D.size < n and D.size != 0:
        raise src.error(f"'{name}' must have {n} coefficients, got {D.size}")
    if np.any(D[n:] != 0):
        raise src.error(f"'{name}' has {D.size} coefficients but this model uses {n}; "
                        f"the extra ones are not zero: {plain_list(D[n:])}")
    return np.pad(D[:n], (0, n - min(n, D.size)))


def _load_kdd(src: Src, data: dict) -> Camera:
    K = _k(src, data["K"], "K")
    D = src.array(src.need(data, "D", hint="K/D/DIM files need the distortion D"), "D",
                  (4, 5, 8, 12))
    if "DIM" in data:
        w, h = src.pixels(src.array(data["DIM"], "DIM", (2,)), "DIM")
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


_USF_MODELS = {0: "pinhole", 1: "mei", "pinhole": "pinhole", "mei": "mei",
               "kannala_brandt": "kannala_brandt"}
#: The parameter names of each model_type: CamOdoCal's (VINS-Mono, VINS-Fusion), whose
#: Kannala-Brandt is OpenCV's fisheye: k2..k5 its k1..k4, mu mv u0 v0 its fx fy cx cy.
_USF_PROJECTION = {"pinhole": ("fx", "fy", "cx", "cy"), "mei": ("gamma1", "gamma2", "u0", "v0"),
                   "kannala_brandt": ("mu", "mv", "u0", "v0")}


def _load_usf(src: Src, data: dict) -> Camera:
    w, h = _size(src, data)
    intr = data.get("intrinsic", data)
    where = "intrinsic" if "intrinsic" in data else ""
    mt = src.need(intr, "model_type", where)
    model = _USF_MODELS.get(mt.lower() if isinstance(mt, str) else mt)
    if model is None:
        raise src.error(f"unknown model_type {mt!r}; supported: 0 or PINHOLE, 1 or MEI, "
                        "KANNALA_BRANDT (CamOdoCal's SCARAMUZZA: give OCamCalib's "
                        "calib_results.txt instead)")
    dp = intr.get("distortion_parameters") or {}
    dist = [src.number(src.need(dp, k, "distortion_parameters"), k) for k in ("k1", "k2", "p1", "p2")] \
        if dp else [0.0] * 4
    pp = src.need(intr, "projection_parameters", where)
    f = [src.number(src.need(pp, k, "projection_parameters"), k) for k in _USF_PROJECTION[model]]
    K = dict(zip(("fx", "fy", "cx", "cy"), f))
    if model == "kannala_brandt":
        k = [src.number(src.need(pp, n, "projection_parameters"), n) for n in ("k2", "k3", "k4", "k5")]
        cam = src.build(KannalaBrandt, **K, width=w, height=h, k=k)
    elif model == "pinhole":
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
    src = Src(Path(path))
    h, w = src.pixels(size, "height width")
    return src.build(Scaramuzza, pol=pol[1:], center=center, affine=affine, width=w, height=h,
                     invpol=invpol[1:])
