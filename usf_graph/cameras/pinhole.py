"""Pinhole cameras: OpenCV's full distortion model, and the one-parameter division model."""

from __future__ import annotations

import numpy as np

from .base import (
    Camera,
    check_finite,
    set_intrinsics,
)
from .distortion import _split_dist, distort, distortion_radius_limit, undistort


class Pinhole(Camera):
    """Perspective camera, ``cv2.projectPoints`` compatible.

    ``dist`` follows OpenCV's order ``k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4]]]``
    (rational radial, tangential, thin prism; OpenCV's tilt terms are not supported).
    Valid rays have z > 0 and a normalized radius inside the disc where the distortion is
    still one-to-one (the radial part increasing and, with tangential or thin-prism
    terms, the Jacobian's determinant positive: ``r_max``), so every valid pixel has
    exactly one ray.
    """

    model = "pinhole"

    def __init__(self, fx, fy, cx, cy, width, height, dist=None, rotation=None):
        super().__init__(width, height, rotation)
        set_intrinsics(self, fx, fy, cx, cy)
        self.dist = _split_dist(check_finite("dist", dist if dist is not None else []))
        self._ncoef = 0 if dist is None else int(np.asarray(dist).size)
        self.r_max = distortion_radius_limit(self.dist)

    def params(self) -> dict:
        return dict(fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy, width=self.width,
                    height=self.height, dist=self.dist[:self._ncoef].tolist() or None)

    def _project(self, rays):
        z = rays[..., 2]
        ok = z > 0
        zs = np.where(ok, z, 1.0)
        x, y = rays[..., 0] / zs, rays[..., 1] / zs
        ok &= np.hypot(x, y) < self.r_max
        xd, yd = distort(self.dist, x, y)
        return np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], -1), ok

    def _unproject(self, uv):
        xd = (uv[..., 0] - self.cx) / self.fx
        yd = (uv[..., 1] - self.cy) / self.fy
        x, y, ok = undistort(self.dist, xd, yd, self.r_max)
        rays = np.stack([x, y, np.ones_like(x)], -1)
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True), ok


class Division(Camera):
    """Fitzgibbon's one-parameter division model (COLMAP's DIVISION and SIMPLE_DIVISION):
    a pixel's normalized coordinates (x_d, y_d) = ((u - cx) / fx, (v - cy) / fy) undistort
    to (x_d, y_d) / (1 + k r_d^2), so its ray is (x_d, y_d, 1 + k r_d^2). Closed form both
    ways: a ray (x, y, z) lands at s (x, y) with s = 2 / (z + sqrt(z^2 - 4 k (x^2 + y^2))).

    With k < 0 (barrel) the model reaches past 90 degrees, where 1 + k r_d^2 turns
    negative; with k > 0 it folds at r_d = 1 / sqrt(k), where its domain ends.
    """

    model = "division"

    def __init__(self, fx, fy, cx, cy, width, height, k, rotation=None):
        super().__init__(width, height, rotation)
        set_intrinsics(self, fx, fy, cx, cy)
        self.k = check_finite("k", k).item()

    def params(self) -> dict:
        return dict(fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy, width=self.width,
                    height=self.height, k=self.k)

    def _project(self, rays):
        x, y, z = rays[..., 0], rays[..., 1], rays[..., 2]
        disc = z * z - 4 * self.k * (x * x + y * y)
        den = z + np.sqrt(np.maximum(disc, 0.0))
        ok = (disc >= 0) & (den > 0)
        s = 2 / np.where(ok, den, 1.0)
        if self.k > 0:  # the smaller root, before the fold
            ok &= self.k * (s * s) * (x * x + y * y) < 1
        return np.stack([self.fx * s * x + self.cx, self.fy * s * y + self.cy], -1), ok

    def _unproject(self, uv):
        xd = (uv[..., 0] - self.cx) / self.fx
        yd = (uv[..., 1] - self.cy) / self.fy
        r2 = xd * xd + yd * yd
        ok = self.k * r2 < 1  # k > 0: before the fold; k <= 0: everywhere
        rays = np.stack([xd, yd, 1 + self.k * r2], -1)
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True), ok
