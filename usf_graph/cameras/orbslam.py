"""ORB-SLAM3's settings files (OpenCV FileStorage): ``Camera.type`` PinHole, KannalaBrandt8 or
Rectified; ``Camera1.fx`` ... (``File.version: "1.0"``) or the older ``Camera.fx`` ...;
``Camera.width``/``Camera.height``; a stereo pair's ``Camera2.*`` mounted by
``Stereo.T_c1_c2`` (the older files: ``Tlr``), which maps Camera2's coordinates to
Camera1's. Pixel centres at integers, as in OpenCV."""

from __future__ import annotations

import numpy as np

from .base import Camera
from .files import Src
from .fisheye import KannalaBrandt
from .pinhole import Pinhole

_TYPES = ("PinHole", "KannalaBrandt8", "Rectified")


def is_orbslam(data: dict) -> bool:
    return any(k in data for k in ("Camera.type", "Camera1.fx", "Camera.fx"))


def orbslam_names(data: dict) -> list[str]:
    if "Camera1.fx" not in data:
        return ["Camera"]
    return ["Camera1"] + (["Camera2"] if "Camera2.fx" in data else [])


def load_orbslam(src: Src, data: dict, name: str) -> Camera:
    kind = str(data.get("Camera.type", "PinHole"))
    if kind not in _TYPES:
        raise src.error(f"ORB-SLAM3 Camera.type '{kind}' is not supported; supported: "
                        f"{', '.join(_TYPES)}")

    def num(key: str, default=None) -> float:
        full = f"{name}.{key}"
        if default is not None and full not in data:
            return default
        return src.number(src.need(data, full), full)

    size = {k: src.pixels(src.number(src.need(data, f"Camera.{k}", hint="ORB-SLAM3 settings give "
                                              "the image size as Camera.width and Camera.height"),
                                     f"Camera.{k}"), f"Camera.{k}")[0] for k in ("width", "height")}
    K = dict(fx=num("fx"), fy=num("fy"), cx=num("cx"), cy=num("cy"), **size)
    if kind == "KannalaBrandt8":
        return src.build(KannalaBrandt, **K, k=[num(f"k{i}") for i in range(1, 5)])
    if kind == "Rectified":
        return src.build(Pinhole, **K)
    dist = [num("k1", 0.0), num("k2", 0.0), num("p1", 0.0), num("p2", 0.0), num("k3", 0.0)]
    return src.build(Pinhole, **K, dist=dist)


def orbslam_pose(path, data: dict, name: str) -> np.ndarray | None:
    """Pose ``[4, 4]`` of ``name``'s optical frame in the first camera's; None when the file
    does not give the pair's extrinsics."""
    if name != "Camera2":
        return np.eye(4)
    key = "Stereo.T_c1_c2" if "Stereo.T_c1_c2" in data else "Tlr"
    if key not in data:
        return None
    return Src(path, name).rigid(data[key], key)  # c1 <- c2


def orbslam_imu(path, data: dict) -> np.ndarray | None:
    """Camera1 <- IMU (body), from ``IMU.T_b_c1``; None when the file has none."""
    if "IMU.T_b_c1" not in data:
        return None
    return np.linalg.inv(Src(path, "IMU").rigid(data["IMU.T_b_c1"], "IMU.T_b_c1"))
