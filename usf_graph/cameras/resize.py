"""A calibration for its images resized: the same lens, another pixel grid.

``cv2.resize`` of a whole frame by ``sx = W' / W`` and ``sy = H' / H`` maps pixel areas onto
pixel areas, so with pixel centres at integers (OpenCV's convention) the point at ``(u, v)``
lands at ``((u + 0.5) sx - 0.5, (v + 0.5) sy - 0.5)`` (:func:`moved`). Every model whose
pixels are an affine map of its projection then keeps its distortion and scales that map:
focal lengths (and Mei's skew) by ``sx``, ``sy``, the principal point as pixels move. Models
with one focal length (the classic fisheyes) and OCamCalib's polynomial in pixels need
``sx == sy``; a panorama spans the same angles at any size; a lens normal map is resampled
through its own interpolation. Each model says how in its ``_resized``; this module, which
imports no model, holds what they share.
"""

from __future__ import annotations

import numpy as np


def resized(cam, width: int, height: int):
    """``cam`` for its images resized to ``width x height`` (the whole frame, no crop). Its
    mounting, position, distance and field-of-view limit stay; an image mask is resized
    with the nearest pixel."""
    width, height = whole_pixels("width", width), whole_pixels("height", height)
    new = cam._resized(width, height, width / cam.width, height / cam.height)
    new.fov_limit, new.position, new.distance = cam.fov_limit, cam.position, cam.distance
    if cam.image_mask is not None:
        import cv2

        new.image_mask = cv2.resize(cam.image_mask.astype(np.uint8), (width, height),
                                    interpolation=cv2.INTER_NEAREST).astype(bool)
    return new


def whole_pixels(name: str, value) -> int:
    """``value`` as an int, refused unless it is a positive whole number of pixels: a size
    of 640.7 would otherwise be truncated without a word."""
    number = np.ndim(value) == 0 and not isinstance(value, (str, bytes))
    try:
        v = float(value) if number else float("nan")
    except (TypeError, ValueError):  # None, an object
        number, v = False, float("nan")
    if not (np.isfinite(v) and v == int(v) and v >= 1):
        shown = str(value) if number else repr(value)
        raise ValueError(f"{name} must be a positive integer number of pixels, got {shown}")
    return int(v)


def moved(c, s: float):
    """Pixel coordinate(s) ``c`` after resizing by ``s``: ``(c + 0.5) s - 0.5``."""
    return (np.asarray(c, np.float64) + 0.5) * s - 0.5


def one_factor(cam, sx: float, sy: float) -> float:
    """``sx``, after checking that the image is resized by one factor: the models with one
    scale for both axes cannot take two."""
    if abs(sx - sy) > 1e-9 * max(sx, sy):
        raise ValueError(f"{type(cam).__name__} has one scale for both image axes: resize its "
                         f"images by one factor (got {sx:.6g} across and {sy:.6g} down)")
    return sx
