"""WoodScape's calibration JSON (Valeo's surround-view fisheyes; also SynWoodScape's): one
camera per file, its ``intrinsic`` a radial polynomial (``model: radial_poly``), its
``extrinsic`` the camera's pose in the vehicle frame."""

from __future__ import annotations

import numpy as np

from ..geometry import rotation_from_quaternion
from .base import Camera
from .files import Src
from .fisheye import RadialPoly


def is_woodscape(data: dict) -> bool:
    """Whether a calibration document is WoodScape's: an ``intrinsic`` map that names the
    ``radial_poly`` model or gives ``cx_offset`` (the USF sensor files share the key
    ``intrinsic``, with a ``model_type``)."""
    intr = data.get("intrinsic")
    return isinstance(intr, dict) and (intr.get("model") == "radial_poly" or
                                       ("cx_offset" in intr and "model_type" not in intr))


def load_woodscape(src: Src, data: dict) -> Camera:
    """The camera of a WoodScape calibration. The principal point is the image's centre plus
    ``cx_offset``, ``cy_offset``, with pixel centres at integers as WoodScape's own code
    has them (``W / 2 + cx_offset - 0.5``). The ``extrinsic`` quaternion (x, y, z, w, as
    SciPy's ``from_quat``) turns the optical frame into the vehicle's, which is the sphere
    frame's convention (x forward, y left, z up; ISO 8855), so it is the camera's
    ``rotation``, and the ``translation`` (metres) its ``position``: the four cameras of a
    car, loaded one file each, are mounted in one frame with gravity along +z."""
    intr = src.need(data, "intrinsic")
    model = intr.get("model", "radial_poly")
    if model != "radial_poly":
        raise src.error(f"WoodScape intrinsic model {model!r} is not supported; only "
                        "'radial_poly'")

    def num(key: str) -> float:
        return src.finite(src.need(intr, key, "intrinsic"), key)

    w, h = num("width"), num("height")
    if w != int(w) or h != int(h) or w < 1 or h < 1:
        raise src.error(f"the image size must be whole positive numbers, got {w} x {h}")
    order = int(intr.get("poly_order", 4))
    k = [num(f"k{i}") for i in range(1, order + 1)]
    cam = src.build(RadialPoly, k=k, cx=w / 2 + num("cx_offset") - 0.5,
                    cy=h / 2 + num("cy_offset") - 0.5, width=int(w), height=int(h),
                    aspect_ratio=num("aspect_ratio") if "aspect_ratio" in intr else 1.0)
    ext = data.get("extrinsic")
    if ext is None:
        return cam
    q = src.array(src.need(ext, "quaternion", "extrinsic"), "quaternion", (4,))
    if not 0.9 < np.linalg.norm(q) < 1.1:
        raise src.error(f"'extrinsic.quaternion' has norm {np.linalg.norm(q):.4g}, not a "
                        "rotation (x, y, z, w)")
    t = src.array(src.need(ext, "translation", "extrinsic"), "translation", (3,))
    T = src.pose(rotation_from_quaternion(np.array([q[3], *q[:3]])), t, "extrinsic")  # w last
    try:
        return cam.with_rotation(T[:3, :3]).with_position(T[:3, 3])
    except ValueError as e:
        raise src.error(str(e)) from None
