"""Basalt's calibration JSON (``value0``: ``intrinsics``, ``resolution``, ``T_imu_cam``): each
camera's model, and its place in the rig from the extrinsics.

Camera types: ``pinhole``, ``pinhole-radtan8`` (OpenCV's 8 coefficients), ``kb4``
(Kannala-Brandt), ``ds`` (Double Sphere), ``eucm``, and ``unified`` (the unified model in
its alpha form: EUCM with beta = 1). Basalt, like Kalibr and OpenCV, puts pixel centres at
integers, so the intrinsics are used as written.
"""

from __future__ import annotations

import numpy as np

from ..geometry import rotation_from_quaternion
from .base import Camera
from .files import Src, plain_list
from .fisheye import KannalaBrandt
from .omni import EUCM, DoubleSphere
from .pinhole import Pinhole

_TYPES = {"pinhole": "fx fy cx cy", "pinhole-radtan8": "fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6",
          "kb4": "fx fy cx cy k1 k2 k3 k4", "ds": "fx fy cx cy xi alpha",
          "eucm": "fx fy cx cy alpha beta", "unified": "fx fy cx cy alpha"}
_OPTIONAL = {"rpmax"}  # radtan8's injective radius: ours is computed from the coefficients


def is_basalt(data: dict) -> bool:
    v = data.get("value0")
    return isinstance(v, dict) and "intrinsics" in v


def basalt_names(data: dict) -> list[str]:
    return [f"cam{i}" for i in range(len(data["value0"]["intrinsics"] or []))]


def load_basalt(src: Src, data: dict, name: str) -> Camera:
    v, i = data["value0"], int(name[3:])
    c = v["intrinsics"][i]
    kind = src.need(c, "camera_type")
    if kind not in _TYPES:
        raise src.error(f"Basalt camera_type '{kind}' is not supported; supported: "
                        f"{', '.join(_TYPES)}")
    want = _TYPES[kind].split()
    p = src.need(c, "intrinsics")
    extra = sorted(set(p) - set(want) - _OPTIONAL) if isinstance(p, dict) else []
    if extra:
        raise src.error(f"Basalt '{kind}' intrinsics are {want}; unexpected {extra}")
    p = {k: src.number(src.need(p, k, "intrinsics"), k) for k in want}
    res = src.array(src.need(v, "resolution"), "resolution")
    if res.size < 2 * (i + 1):
        raise src.error(f"'resolution' lists {res.size // 2} cameras' sizes, but this is "
                        f"camera {i}: {plain_list(res)}")
    w, h = src.pixels(res[2 * i:2 * i + 2], "resolution")
    K = dict(fx=p["fx"], fy=p["fy"], cx=p["cx"], cy=p["cy"], width=w, height=h)
    if kind == "pinhole":
        return src.build(Pinhole, **K)
    if kind == "pinhole-radtan8":
        return src.build(Pinhole, **K, dist=[p[k] for k in want[4:]])
    if kind == "kb4":
        return src.build(KannalaBrandt, **K, k=[p[k] for k in want[4:]])
    if kind == "ds":
        return src.build(DoubleSphere, **K, xi=p["xi"], alpha=p["alpha"])
    return src.build(EUCM, **K, alpha=p["alpha"], beta=p.get("beta", 1.0))


def _imu_from_cam(src: Src, T) -> np.ndarray:
    """``T_imu_cam`` (px, py, pz, qx, qy, qz, qw) as ``[4, 4]``."""
    q = [src.number(src.need(T, k, "T_imu_cam"), k) for k in ("qx", "qy", "qz", "qw")]
    if not 0.9 < np.linalg.norm(q) < 1.1:
        raise src.error(f"'T_imu_cam' has a quaternion of norm {np.linalg.norm(q):.4g}, not a "
                        "rotation")
    t = [src.number(src.need(T, k, "T_imu_cam"), k) for k in ("px", "py", "pz")]
    return src.pose(rotation_from_quaternion(np.array([q[3], *q[:3]])), t, "T_imu_cam")  # w last


def basalt_pose(path, data: dict, name: str) -> np.ndarray | None:
    """Pose ``[4, 4]`` of ``name``'s optical frame in cam0's, from both cameras'
    ``T_imu_cam``; None when the file has none."""
    T = data["value0"].get("T_imu_cam") or []
    i = int(name[3:])
    if i == 0:
        return np.eye(4)
    if len(T) <= i:
        return None
    return basalt_imu(path, data) @ _imu_from_cam(Src(path, name), T[i])  # c0 <- IMU <- ci


def basalt_imu(path, data: dict) -> np.ndarray | None:
    """cam0 <- IMU, from cam0's ``T_imu_cam``; None when the file has none."""
    T = data["value0"].get("T_imu_cam") or []
    return np.linalg.inv(_imu_from_cam(Src(path, "cam0"), T[0])) if T else None


def basalt_clock(path, data: dict, name: str) -> int:
    """``cam_time_offset_ns`` (t_imu = t_cam + offset; one for every camera)."""
    return round(Src(path, "value0").finite(data["value0"].get("cam_time_offset_ns", 0),
                                            "cam_time_offset_ns"))
