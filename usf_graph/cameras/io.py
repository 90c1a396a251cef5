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
- ORB-SLAM3's settings (FileStorage): ``Camera.type`` PinHole | KannalaBrandt8 | Rectified,
  ``Camera1.*``/``Camera2.*`` (or the older ``Camera.*``), mounted by ``Stereo.T_c1_c2``.
- Basalt's calibration JSON (``value0``: ``intrinsics``, ``resolution``, ``T_imu_cam``):
  pinhole | pinhole-radtan8 | kb4 | ds | eucm | unified, mounted in the rig.
- COLMAP's ``cameras.txt``/``cameras.bin``, or a sparse model's folder holding one
  (:mod:`.colmap`); ``key`` is the camera's id.

Every error names the file, the key and what would be accepted.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .basalt import basalt_clock, basalt_imu, basalt_names, basalt_pose, is_basalt, load_basalt
from .base import DEFAULT_ROTATION, FORMAT_TAG, Camera
from .colmap import CameraList, colmap_rig, in_folder, read_file, rig_file
from .files import FORMATS, Src, plain_list, read_document, read_mask
from .fisheye import FOV, Fisheye, KannalaBrandt
from .kalibr import is_kalibr, kalibr_clock, kalibr_imu, kalibr_names, kalibr_pose, load_kalibr
from .omni import EUCM, DoubleSphere, Mei
from .orbslam import is_orbslam, load_orbslam, orbslam_imu, orbslam_names, orbslam_pose
from .panorama import Equirectangular, LensNormalMap
from .pinhole import Division, Pinhole
from .rig import mount
from .scaramuzza import Scaramuzza

MODELS = {c.__name__: c for c in (Pinhole, Division, Fisheye, KannalaBrandt, FOV, Mei,
                                  DoubleSphere, EUCM, Scaramuzza, Equirectangular)}
_PINHOLE_DIST = ("plumb_bob", "rational_polynomial", "pinhole", "radtan")
_FISHEYE_DIST = ("equidistant", "fisheye", "kannala-brandt", "kb4")


def load(path, key: str | None = None, fov_deg: float | None = None, image_mask=None) -> Camera:
    """Read a camera from a calibration file in any of the formats of this module.

    Args:
        path: the file.
        key: the camera in a Kalibr camchain or a Basalt calibration (``cam0`` by
            default), in ORB-SLAM3 stereo settings (``Camera1`` by default) or in a COLMAP
            camera list (its id; needed when the list holds several); ``--key`` on the
            command line. An error for files that hold one camera.
        fov_deg: optional usable field of view (:meth:`Camera.with_fov`), over the file's.
        image_mask: optional ``[H, W]`` mask or image file, over the file's.

    A camera of a Kalibr chain, a Basalt calibration or ORB-SLAM3 stereo settings comes
    back mounted in the rig: its ``rotation`` is the rotation from its optical frame to the
    rig's sphere frame, which is the first camera's (it looks along +x). See
    :func:`load_rig` for all of them at once.
    """
    path = Path(path)
    data = _document(path)
    if isinstance(data, CameraList):
        cam, fmt = data.pick(key), None
    elif (chain := _chain(data)) is not None:
        names = chain.names(data)
        key = key or names[0]
        if key not in names:
            raise ValueError(f"{path}: no camera '{key}' in the {chain.kind} (it has {names}); "
                             "choose one with key= (--key on the command line)")
        cam, fmt = _mounted(path, data, chain, key), None
    else:
        fmt, cam = _one(path, data)
    if key is not None and fmt is not None:
        raise ValueError(f"{path}: key={key!r} (--key) picks a camera in a Kalibr camchain, a "
                         "Basalt calibration, ORB-SLAM3 stereo settings or a COLMAP camera "
                         f"list, but this is {'an' if fmt[0] in 'AEIOU' else 'a'} {fmt} file "
                         "with one camera; leave the key out")
    return with_fov_and_mask(cam, fov_deg, image_mask)


def load_all(path) -> dict:
    """Every camera of a calibration file, by the key :func:`load` takes for it: a Kalibr
    camchain's, Basalt calibration's or ORB-SLAM3 stereo pair's names (each mounted in the
    rig where the file says how), a COLMAP list's ids; ``{None: camera}`` for a file that
    holds one camera."""
    path = Path(path)
    data = _document(path)
    if isinstance(data, CameraList):
        return {i: data.pick(i) for i in sorted(data)}
    if (chain := _chain(data)) is not None:
        return {name: _mounted(path, data, chain, name) for name in chain.names(data)}
    return {None: _one(path, data)[1]}


def _one(path: Path, data) -> tuple:
    """(format name, camera) of a file that holds one camera."""
    if isinstance(data, Camera):
        return ("OCamCalib" if isinstance(data, Scaramuzza) else "lens normal map"), data
    return _load_single(path, data)


def _mounted(path: Path, data: dict, chain, name: str, required: bool = False) -> Camera:
    """Camera ``name`` of a rig's file, mounted in the rig where the file says how (and
    where it does not, an error if ``required``)."""
    pose = chain.pose(path, data, name)
    if pose is None and required:
        raise ValueError(f"{path} [{name}]: no {chain.extrinsics}, so its place in the rig "
                         "is unknown; add the extrinsics")
    cam = chain.camera(Src(path, name), data, name)
    return cam if pose is None else mount(cam, pose)



def rig_topics(path) -> list[str] | None:
    """The ROS image topic of each camera of a Kalibr camchain (its ``rostopic``s, in the
    rig's order), or None where the file does not name them all."""
    path = Path(path)
    if rig_file(path) is not None:
        return None
    data = _document(path)
    chain = _chain(data)
    if chain is None or chain.kind != "camchain":
        return None
    found = [data[n].get("rostopic") for n in chain.names(data)]
    return found if all(isinstance(t, str) and t for t in found) else None


def imu_rotation(path) -> np.ndarray:
    """``[3, 3]``: the IMU's frame -> the sphere frame of the file's cameras (the rig's, as
    :func:`load` and :func:`load_rig` mount them), from a Kalibr camchain's ``T_cam_imu``
    (camchain-imucam), a Basalt calibration's ``T_imu_cam`` or ORB-SLAM3's ``IMU.T_b_c1``.
    Turns an accelerometer's reading into the cameras' ``up``."""
    path = Path(path)
    data = _document(path)
    chain = _chain(data)
    T = None if chain is None else chain.imu(path, data)
    if T is None:
        raise ValueError(f"{path}: no camera-IMU extrinsics, so the IMU's readings cannot be "
                         "turned into the camera's frame; give a Kalibr camchain-imucam "
                         "(T_cam_imu), a Basalt calibration (T_imu_cam) or ORB-SLAM3 settings "
                         "(IMU.T_b_c1)")
    return DEFAULT_ROTATION @ T[:3, :3]


def imu_time_shift(path, key: str | None = None) -> int:
    """Nanoseconds to add to camera ``key``'s stamps (default: the first camera) to read
    the IMU's clock at the same instant: Kalibr's ``timeshift_cam_imu`` (camchain-imucam;
    t_imu = t_cam + shift, in seconds), Basalt's ``cam_time_offset_ns``; 0 where the file
    gives none (ORB-SLAM3 has no such field)."""
    path = Path(path)
    data = _document(path)
    chain = _chain(data)
    if chain is None:
        raise ValueError(f"{path}: not a Kalibr camchain, Basalt calibration or ORB-SLAM3 "
                         "settings, so it has no camera-IMU time shift")
    names = chain.names(data)
    if key is not None and key not in names:
        raise ValueError(f"{path}: no camera '{key}' in the {chain.kind} (it has {names})")
    return chain.clock(path, data, key or names[0])


def with_fov_and_mask(cam: Camera, fov_deg: float | None = None, image_mask=None) -> Camera:
    """``cam`` with a usable field of view (:meth:`Camera.with_fov`) and an image mask
    (``[H, W]`` array, or an image file: :func:`read_mask`), each where given."""
    if fov_deg is not None:
        cam = cam.with_fov(fov_deg)
    if image_mask is not None:
        cam = cam.with_image_mask(read_mask(image_mask) if isinstance(image_mask, (str, Path))
                                  else image_mask)
    return cam


def load_rig(path, key=None) -> dict[str, Camera]:
    """All cameras of a Kalibr camchain, a Basalt calibration or ORB-SLAM3 settings, each
    mounted in the rig (the first camera's frame, looking along +x), in the file's order.
    Every camera after the first needs its extrinsics (Kalibr: ``T_cn_cnm1``, or each a
    ``T_cam_imu``; Basalt: ``T_imu_cam``; ORB-SLAM3: ``Stereo.T_c1_c2``). Each camera's
    ``position`` is its optical centre in that frame, in the file's unit (metres); it
    matters once a :class:`~usf_graph.frontend.RigFrontend` stitches at a finite
    ``distance`` (:func:`stitch_at`). Without one the rig is treated as one centre of
    projection, which holds for scenes far away compared to the baseline.

    A COLMAP model's folder with ``rigs.txt``/``rigs.bin`` (COLMAP 3.12 on), or that file:
    the rig ``key`` (its id; needed when there are several), its cameras named by their
    ids and mounted by their ``sensor_from_rig`` poses."""
    path = Path(path)
    if rig_file(path) is not None:
        return colmap_rig(path, key)
    if key is not None:
        raise ValueError(f"{path}: key={key!r} (--key) picks a rig in a COLMAP model; this "
                         "file holds one rig, whose every camera is used: leave the key out")
    data = _document(path)
    chain = _chain(data)
    if chain is None:
        raise ValueError(f"{path}: a rig is read from a Kalibr camchain (cam0, cam1, ... with "
                         "T_cn_cnm1), a Basalt calibration (T_imu_cam), ORB-SLAM3 settings "
                         "(Stereo.T_c1_c2) or a COLMAP model with rigs.txt; this file is none, "
                         "so read its cameras one by one with cameras.load")
    return {name: _mounted(path, data, chain, name, required=True) for name in chain.names(data)}


class _Chain(NamedTuple):
    """A file format that holds a rig's cameras, cam0 first."""
    kind: str
    test: Callable
    names: Callable  # data -> camera names
    camera: Callable  # (Src, data, name) -> Camera in its optical frame
    pose: Callable  # (path, data, name) -> [4, 4] cam0's optical frame <- its, or None
    extrinsics: str  # what an error asks for
    imu: Callable  # (path, data) -> [4, 4] cam0's optical frame <- the IMU's, or None
    clock: Callable  # (path, data, name) -> ns that turn the camera's stamps into the IMU's


_CHAINS = (
    _Chain("camchain", is_kalibr, kalibr_names, lambda src, data, name: load_kalibr(src, data[name]),
           kalibr_pose, "'T_cn_cnm1' (or 'T_cam_imu' on it and on cam0)", kalibr_imu,
           kalibr_clock),
    _Chain("Basalt calibration", is_basalt, basalt_names, load_basalt, basalt_pose,
           "'T_imu_cam' for it", basalt_imu, basalt_clock),
    _Chain("ORB-SLAM3 settings", is_orbslam, orbslam_names, load_orbslam, orbslam_pose,
           "'Stereo.T_c1_c2' (or 'Tlr')", orbslam_imu, lambda path, data, name: 0))


def _chain(data) -> _Chain | None:
    if not isinstance(data, dict) or isinstance(data, CameraList):
        return None
    return next((c for c in _CHAINS if c.test(data)), None)


def _document(path: Path):
    """A calibration file's content: a camera, a COLMAP camera list or a dict of the file."""
    if path.is_dir():
        path = in_folder(path)
    if not path.is_file():
        raise FileNotFoundError(f"calibration file {path} does not exist")
    if path.suffix not in (".npy", ".npz"):
        cams = read_file(path)
        if cams is not None:
            return cams
    return read_document(path, _load_ocamcalib)


def save(cam: Camera, path) -> None:
    """Write ``cam`` in usf-graph's YAML form, atomically (:meth:`Camera.save`)."""
    cam.save(path)


def _load_single(path: Path, data: dict):
    """(format name, camera) for every format that holds one camera."""
    src = Src(path)
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


def _size(src: Src, data: dict) -> tuple[int, int]:
    hint = "give the image size as image_width and image_height"
    w, h = (src.number(src.need(data, k, hint=hint), k) for k in ("image_width", "image_height"))
    return int(w), int(h)


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


def _load_usf(src: Src, data: dict) -> Camera:
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
    return Src(Path(path)).build(Scaramuzza, pol=pol[1:], center=center, affine=affine,
                                  width=w, height=h, invpol=invpol[1:])

