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
  (``.npy``), paths relative to the file. CamOdoCal's flat form (VINS-Mono, VINS-Fusion:
  ``model_type`` PINHOLE, MEI or KANNALA_BRANDT) too.
- OCamCalib ``calib_results.txt``; lens normal maps ``.npy``/``.npz`` (``rays``, ``valid``).
- usf-graph's own YAML (:meth:`Camera.save`), with optional ``fov_deg`` and ``image_mask``.
- ORB-SLAM3's settings (FileStorage): ``Camera.type`` PinHole | KannalaBrandt8 | Rectified,
  ``Camera1.*``/``Camera2.*`` (or the older ``Camera.*``), mounted by ``Stereo.T_c1_c2``.
- Basalt's calibration JSON (``value0``: ``intrinsics``, ``resolution``, ``T_imu_cam``):
  pinhole | pinhole-radtan8 | kb4 | ds | eucm | unified, mounted in the rig.
- COLMAP's ``cameras.txt``/``cameras.bin``, or a sparse model's folder holding one
  (:mod:`.colmap`); ``key`` is the camera's id.
- Nerfstudio's and Instant-NGP's ``transforms.json`` (:mod:`.nerfstudio`): OPENCV and
  the pinholes, OPENCV_FISHEYE, EQUIRECTANGULAR; ``key`` is a frame's ``file_path`` where
  the frames have intrinsics of their own.

Every error names the file, the key and what would be accepted.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .basalt import basalt_clock, basalt_imu, basalt_names, basalt_pose, is_basalt, load_basalt
from .base import DEFAULT_ROTATION, Camera
from .colmap import CameraList, colmap_rig, in_folder, read_file, rig_file
from .files import Src, read_document
from .formats import _load_ocamcalib, _load_single, with_fov_and_mask
from .kalibr import is_kalibr, kalibr_clock, kalibr_imu, kalibr_names, kalibr_pose, load_kalibr
from .nerfstudio import TransformsCameras, is_transforms, read_transforms
from .orbslam import is_orbslam, load_orbslam, orbslam_imu, orbslam_names, orbslam_pose
from .rig import mount
from .scaramuzza import Scaramuzza


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
                         f"list, but this is {'an' if fmt[0] in 'AEIO' else 'a'} {fmt} file "  # "a USF": as spoken
                         "with one camera; leave the key out")
    return with_fov_and_mask(cam, fov_deg, image_mask)


def load_all(path) -> dict:
    """Every camera of a calibration file, by the key :func:`load` takes for it: a Kalibr
    camchain's, Basalt calibration's or ORB-SLAM3 stereo pair's names (each mounted in the
    rig where the file says how), a COLMAP list's ids; ``{None: camera}`` for a file that
    holds one camera; a list of files of one posed camera each: :func:`load_rig`'s."""
    if isinstance(path, (list, tuple)):
        return _rig_of_files(path, None)
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


def frame_key(path, image) -> str | None:
    """The key that picks the camera of the image file ``image`` in the calibration file
    ``path`` where its frames have intrinsics of their own (a ``transforms.json`` frame
    whose ``file_path``, from the file's folder, is ``image``); None for other files, and
    for images it does not list."""
    path = Path(path)
    if image is None or path.suffix.lower() != ".json" or not path.is_file():
        return None
    st = path.stat()  # predict asks for every frame: the file is read once while it stays
    return _frame_keys(str(path.resolve()), st.st_mtime_ns, st.st_size).get(Path(image).resolve())


@functools.lru_cache(maxsize=8)
def _frame_keys(path: str, mtime_ns: int, size: int) -> dict:
    """``{image path, resolved: key}`` of a ``transforms.json`` whose frames have cameras of
    their own, ``{}`` for any other file (``mtime_ns`` and ``size``: the cache's key only)."""
    data = _document(Path(path))
    if not isinstance(data, TransformsCameras) or list(data) == [None]:
        return {}
    found: dict = {}
    for k in data:  # the first frame listing an image keeps it
        found.setdefault((Path(path).parent / k).resolve(), k)
    return found


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
    ids and mounted by their ``sensor_from_rig`` poses.

    A list of files of one camera each, every one with its pose in one common frame (a
    ``position``: WoodScape's calibrations, a car's cameras in its vehicle frame, or
    usf-graph YAMLs saved from a rig): those cameras, named by the files' stems."""
    if isinstance(path, (list, tuple)):
        return _rig_of_files(path, key)
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


def _rig_of_files(paths: list, key) -> dict[str, Camera]:
    """:func:`load_rig` of one file per camera, each posed in one frame."""
    paths = [Path(p) for p in paths]
    if key is not None:
        raise ValueError(f"key={key!r} (--key) picks a rig in a COLMAP model; a rig of "
                         "separate files uses every file: leave the key out")
    names = [p.stem for p in paths]
    if len(paths) < 2 or len(set(names)) != len(names):
        raise ValueError(f"a rig of separate calibration files needs two or more, with "
                         f"different names, got {[str(p) for p in paths]}")
    rig = {}
    for name, p in zip(names, paths):
        cam = load(p)
        if cam.position is None:
            raise ValueError(f"{p}: the camera has no pose in the rig (no position), so it "
                             "cannot join others from separate files; give a file with its "
                             "extrinsics (WoodScape's calibration, a usf-graph YAML saved from "
                             "a rig) or one rig file (a Kalibr camchain, ...)")
        rig[name] = cam
    return rig


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
    data = read_document(path, _load_ocamcalib)
    return read_transforms(path, data) if is_transforms(data) else data


def save(cam: Camera, path) -> None:
    """Write ``cam`` in usf-graph's YAML form, atomically (:meth:`Camera.save`)."""
    cam.save(path)
