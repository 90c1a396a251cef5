"""A calibration for its images resized: the same lens, another pixel grid.

``cv2.resize`` of a whole frame by ``sx = W' / W`` and ``sy = H' / H`` maps pixel areas onto
pixel areas, so with pixel centres at integers (OpenCV's convention) the point at ``(u, v)``
lands at ``((u + 0.5) sx - 0.5, (v + 0.5) sy - 0.5)``. Every model whose pixels are an
affine map of its projection then keeps its distortion and scales that map: focal lengths
(and Mei's skew) by ``sx``, ``sy``, the principal point as pixels move. Models with one
focal length (the classic fisheyes) and OCamCalib's polynomial in pixels need ``sx == sy``;
a panorama spans the same angles at any size; a lens normal map is resampled through its
own interpolation.
"""

from __future__ import annotations

import numpy as np

from .base import Camera
from .panorama import Equirectangular, LensNormalMap
from .scaramuzza import Scaramuzza


def resized(cam: Camera, width: int, height: int) -> Camera:
    """``cam`` for its images resized to ``width x height`` (the whole frame, no crop). Its
    mounting, position, distance and field-of-view limit stay; an image mask is resized
    with the nearest pixel."""
    width, height = int(width), int(height)
    if width < 1 or height < 1:
        raise ValueError(f"a resized camera needs a positive size, got {width} x {height}")
    sx, sy = width / cam.width, height / cam.height
    new = _same_lens(cam, width, height, sx, sy)
    new.fov_limit, new.position, new.distance = cam.fov_limit, cam.position, cam.distance
    if cam.image_mask is not None:
        import cv2

        new.image_mask = cv2.resize(cam.image_mask.astype(np.uint8), (width, height),
                                    interpolation=cv2.INTER_NEAREST).astype(bool)
    return new


def _same_lens(cam: Camera, width: int, height: int, sx: float, sy: float) -> Camera:
    p = dict(cam.params(), width=width, height=height)
    if isinstance(cam, LensNormalMap):
        u, v = np.meshgrid((np.arange(width) + 0.5) / sx - 0.5,
                           (np.arange(height) + 0.5) / sy - 0.5)
        rays, ok = cam.unproject(np.stack([u, v], -1))
        return LensNormalMap(rays, ok, cam.rotation, cam.source)
    if isinstance(cam, Equirectangular):
        return Equirectangular(**p, rotation=cam.rotation)
    uniform = abs(sx - sy) <= 1e-9 * max(sx, sy)
    if isinstance(cam, Scaramuzza):
        _uniform(cam, uniform, sx, sy)
        # the sensor radius scales by s: pol'(s r) = s pol(r), and so does invpol's rho
        p["pol"] = [a * sx ** (1 - i) for i, a in enumerate(cam.pol)]
        p["center"] = [(c + 0.5) * sx - 0.5 for c in cam.center]
        p["invpol"] = None if cam.invpol is None else [a * sx for a in cam.invpol]
    elif "fx" in p:
        p.update(fx=cam.fx * sx, fy=cam.fy * sy, cx=(cam.cx + 0.5) * sx - 0.5,
                 cy=(cam.cy + 0.5) * sy - 0.5)
        if "skew" in p:
            p["skew"] = cam.skew * sx
    elif "f" in p:
        _uniform(cam, uniform, sx, sy)
        p.update(f=cam.f * sx, cx=(cam.cx + 0.5) * sx - 0.5, cy=(cam.cy + 0.5) * sy - 0.5)
    else:
        raise ValueError(f"{type(cam).__name__} cannot be resized")
    return type(cam)(**p, rotation=cam.rotation)


def _uniform(cam: Camera, uniform: bool, sx: float, sy: float) -> None:
    if not uniform:
        raise ValueError(f"{type(cam).__name__} has one scale for both image axes: resize its "
                         f"images by one factor (got {sx:.6g} across and {sy:.6g} down)")
