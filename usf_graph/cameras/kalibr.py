"""Kalibr camchains: each camera's model, and its place in the rig from the extrinsics."""

from __future__ import annotations

import numpy as np

from .base import Camera
from .files import Src, plain_list
from .fisheye import KannalaBrandt
from .omni import EUCM, DoubleSphere, Mei
from .pinhole import Pinhole

# Kalibr's intrinsics per camera_model, and the (model, distortion) pairs we read.
_KALIBR_INTRINSICS = {"pinhole": "fu fv pu pv", "omni": "xi fu fv pu pv",
                      "ds": "xi alpha fu fv pu pv", "eucm": "alpha beta fu fv pu pv"}
_KALIBR_DIST = {"radtan": 4, "equidistant": 4, "none": 0}
_KALIBR_PAIRS = ("pinhole-radtan", "pinhole-equidistant", "pinhole-none", "omni-radtan",
                 "omni-none", "ds-none", "eucm-none")


def is_kalibr(data: dict) -> bool:
    return any(isinstance(v, dict) and "camera_model" in v for v in data.values())


def kalibr_names(data: dict) -> list[str]:
    return [k for k, v in data.items() if isinstance(v, dict) and "camera_model" in v]


def load_kalibr(src: Src, c: dict) -> Camera:
    model = src.need(c, "camera_model")
    if model not in _KALIBR_INTRINSICS:
        raise src.error(f"unknown Kalibr camera_model '{model}'; supported: "
                        f"{', '.join(_KALIBR_INTRINSICS)}")
    names = _KALIBR_INTRINSICS[model].split()
    intr = src.array(src.need(c, "intrinsics"), "intrinsics")
    if intr.size != len(names):
        raise src.error(f"Kalibr '{model}' intrinsics are [{', '.join(names)}] ({len(names)} "
                        f"values), got {intr.size}: {plain_list(intr)}")
    p = dict(zip(names, intr.tolist()))
    dm = c.get("distortion_model", "none")
    if f"{model}-{dm}" not in _KALIBR_PAIRS:
        raise src.error(f"Kalibr {model}-{dm} is not supported; supported: {', '.join(_KALIBR_PAIRS)}")
    dist = src.array(c.get("distortion_coeffs") or [], "distortion_coeffs")
    if dist.size != _KALIBR_DIST[dm]:
        raise src.error(f"Kalibr distortion_model '{dm}' takes {_KALIBR_DIST[dm]} "
                        f"distortion_coeffs, got {dist.size}")
    w, h = src.pixels(src.array(src.need(c, "resolution"), "resolution", (2,)), "resolution")
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


def kalibr_pose(path, data: dict, key: str) -> np.ndarray | None:
    """Pose ``[4, 4]`` of ``key``'s optical frame in cam0's (cam0 <- key, metres), from the
    T_cn_cnm1 chain (or both cameras' T_cam_imu); None when the file does not say."""
    names = kalibr_names(data)
    idx = names.index(key)
    T = np.eye(4)
    for name in names[1:idx + 1]:
        step = data[name].get("T_cn_cnm1")
        if step is None:
            break
        T = T @ np.linalg.inv(Src(path, name).rigid(step, "T_cn_cnm1"))  # c0 <- cn
    else:
        return T
    c0_imu, tk = kalibr_imu(path, data), data[key].get("T_cam_imu")
    if c0_imu is None or tk is None:
        return None
    return c0_imu @ np.linalg.inv(Src(path, key).rigid(tk, "T_cam_imu"))


def kalibr_imu(path, data: dict) -> np.ndarray | None:
    """cam0's pose in the IMU's frame inverted: ``T_cam_imu`` of cam0 (cam0 <- IMU), or None."""
    name = kalibr_names(data)[0]
    T = data[name].get("T_cam_imu")
    return None if T is None else Src(path, name).rigid(T, "T_cam_imu")


def kalibr_clock(path, data: dict, name: str) -> int:
    """Camera ``name``'s ``timeshift_cam_imu`` (seconds; t_imu = t_cam + shift) in ns."""
    return round(Src(path, name).finite(data[name].get("timeshift_cam_imu", 0.0),
                                        "timeshift_cam_imu") * 1e9)


# -- OCamCalib -----------------------------------------------------------------------------
