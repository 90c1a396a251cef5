"""Central catadioptric / wide-angle models: Mei (unified) and Double Sphere."""

from __future__ import annotations

import numpy as np

from .base import (
    Camera,
    check_finite,
    check_positive,
    set_intrinsics,
)
from .distortion import _split_dist, distort, distortion_radius_limit, undistort
from .radial import incidence, monotone_limit


def _fold_limit(cam: Camera, w: float) -> float:
    """Largest incidence below the model's bound z > -w |X| up to which the image radius
    keeps growing (``cam._project`` before ``theta_max`` exists)."""
    w = float(np.clip(w, -1, 1))
    t_w = float(np.arctan2(np.sqrt(1 - w * w), -w))
    radius = lambda t: cam._project(np.stack([np.sin(t), 0 * t, np.cos(t)], -1))[0][..., 0]  # noqa: E731
    return monotone_limit(lambda t: radius(t) - cam.cx, t_w)


class Mei(Camera):
    """Unified omnidirectional model (Mei & Rives 2007), as ``cv2.omnidir``.

    The ray is put on the unit sphere, projected from the point (0, 0, -xi), distorted
    with radtan ``dist = (k1, k2, p1, p2)`` and mapped by K (with optional ``skew``).
    Valid rays satisfy s_z > -xi' (xi' = xi, or 1/xi when xi > 1), and their projected
    point stays inside the disc where the distortion is one-to-one (``r_max``, as the
    pinhole's).
    """

    model = "mei"

    def __init__(self, fx, fy, cx, cy, width, height, xi, dist=(0.0, 0.0, 0.0, 0.0), skew=0.0,
                 rotation=None):
        super().__init__(width, height, rotation)
        set_intrinsics(self, fx, fy, cx, cy)
        self.xi = check_finite("xi", xi).item()
        if self.xi < 0:
            raise ValueError(f"Mei xi must be >= 0 (the mirror parameter), got {self.xi}")
        d = check_finite("dist", dist)
        if d.size != 4:
            raise ValueError(f"Mei dist must be radtan (k1, k2, p1, p2), got {d.tolist()}")
        self.dist = _split_dist(d)
        self.skew = check_finite("skew", skew).item()
        self.r_max = distortion_radius_limit(self.dist)
        self._xi_lim = self.xi if self.xi <= 1 else 1 / self.xi

    def params(self) -> dict:
        return dict(fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy, width=self.width,
                    height=self.height, xi=self.xi, dist=self.dist[:4].tolist(), skew=self.skew)

    def _project(self, rays):
        s = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
        den = s[..., 2] + self.xi
        ok = (s[..., 2] > -self._xi_lim) & (den > 0)
        den = np.where(ok, den, 1.0)
        mx, my = s[..., 0] / den, s[..., 1] / den
        ok &= np.hypot(mx, my) < self.r_max
        xd, yd = distort(self.dist, mx, my)
        return np.stack([self.fx * xd + self.skew * yd + self.cx, self.fy * yd + self.cy], -1), ok

    def _unproject(self, uv):
        yd = (uv[..., 1] - self.cy) / self.fy
        xd = (uv[..., 0] - self.cx - self.skew * yd) / self.fx
        mx, my, ok = undistort(self.dist, xd, yd, self.r_max)
        r2 = mx * mx + my * my
        disc = 1 + (1 - self.xi ** 2) * r2
        ok &= disc >= 0
        f = (self.xi + np.sqrt(np.maximum(disc, 0))) / (1 + r2)
        rays = np.stack([f * mx, f * my, f - self.xi], -1)
        ok &= rays[..., 2] > -self._xi_lim  # the other root belongs to the hidden sheet
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True), ok


class DoubleSphere(Camera):
    """Double Sphere model (Usenko, Demmel & Cremers 2018), closed form both ways.

    Parameters as basalt orders them: fx, fy, cx, cy, xi in (-1, 1], alpha in [0, 1].
    """

    model = "double-sphere"

    def __init__(self, fx, fy, cx, cy, width, height, xi, alpha, rotation=None):
        super().__init__(width, height, rotation)
        set_intrinsics(self, fx, fy, cx, cy)
        self.xi, self.alpha = check_finite("xi", xi).item(), check_finite("alpha", alpha).item()
        if not -1 < self.xi <= 1:
            raise ValueError(f"DoubleSphere xi must lie in (-1, 1], got {self.xi}")
        if not 0 <= self.alpha <= 1:
            raise ValueError(f"DoubleSphere alpha must lie in [0, 1], got {self.alpha}")
        a = self.alpha
        w1 = a / (1 - a) if a <= 0.5 else (1 - a) / a
        self._w2 = (w1 + self.xi) / np.sqrt(2 * w1 * self.xi + self.xi ** 2 + 1)
        # The paper's condition z > -w2 |X| does not exclude every fold (e.g. xi < 0 with
        # alpha near 1), so the honest domain also stops where the image radius stops
        # growing with the incidence angle.
        self.theta_max = _fold_limit(self, self._w2)

    def params(self) -> dict:
        return dict(fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy, width=self.width,
                    height=self.height, xi=self.xi, alpha=self.alpha)

    def _project(self, rays):
        x, y, z = rays[..., 0], rays[..., 1], rays[..., 2]
        d1 = np.linalg.norm(rays, axis=-1)
        k = self.xi * d1 + z
        d2 = np.sqrt(x * x + y * y + k * k)
        den = self.alpha * d2 + (1 - self.alpha) * k
        ok = (z > -self._w2 * d1) & (den > 0)
        if hasattr(self, "theta_max"):
            ok &= incidence(rays) < self.theta_max
        den = np.where(ok, den, 1.0)
        return np.stack([self.fx * x / den + self.cx, self.fy * y / den + self.cy], -1), ok

    def _unproject(self, uv):
        a, xi = self.alpha, self.xi
        mx = (uv[..., 0] - self.cx) / self.fx
        my = (uv[..., 1] - self.cy) / self.fy
        r2 = mx * mx + my * my
        ok = np.ones(r2.shape, bool) if a <= 0.5 else r2 < 1 / (2 * a - 1)
        mz = (1 - a * a * r2) / (a * np.sqrt(np.maximum(1 - (2 * a - 1) * r2, 0)) + 1 - a)
        disc = mz * mz + (1 - xi * xi) * r2
        ok &= disc >= 0
        s = (mz * xi + np.sqrt(np.maximum(disc, 0))) / (mz * mz + r2)
        rays = np.stack([s * mx, s * my, s * mz - xi], -1)
        rays = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
        ok &= (rays[..., 2] > -self._w2) & (incidence(rays) < self.theta_max)
        return rays, ok


class EUCM(Camera):
    """Enhanced Unified Camera Model (Khomutenko, Garcia & Martinet 2016), closed form.

    With d = sqrt(beta (x^2 + y^2) + z^2) and den = alpha d + (1 - alpha) z, a ray maps to
    u = fx x / den + cx, v = fy y / den + cy. ``alpha`` in [0, 1], ``beta`` > 0; beta = 1 is
    Mei's model with xi = alpha / (1 - alpha). Kalibr orders the intrinsics
    [alpha, beta, fu, fv, pu, pv]; basalt [fx, fy, cx, cy, alpha, beta].
    """

    model = "eucm"

    def __init__(self, fx, fy, cx, cy, width, height, alpha, beta, rotation=None):
        super().__init__(width, height, rotation)
        set_intrinsics(self, fx, fy, cx, cy)
        self.alpha = check_finite("alpha", alpha).item()
        self.beta = check_positive("beta", beta, "EUCM's beta shapes the projection ellipsoid.")
        if not 0 <= self.alpha <= 1:
            raise ValueError(f"EUCM alpha must lie in [0, 1], got {self.alpha}")
        a = self.alpha
        self._w = a / (1 - a) if a <= 0.5 else (1 - a) / a
        self.theta_max = _fold_limit(self, self._w)  # as for the Double Sphere

    def params(self) -> dict:
        return dict(fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy, width=self.width,
                    height=self.height, alpha=self.alpha, beta=self.beta)

    def _project(self, rays):
        x, y, z = rays[..., 0], rays[..., 1], rays[..., 2]
        d = np.sqrt(self.beta * (x * x + y * y) + z * z)
        den = self.alpha * d + (1 - self.alpha) * z
        ok = (z > -self._w * d) & (den > 0)
        if hasattr(self, "theta_max"):
            ok &= incidence(rays) < self.theta_max
        den = np.where(ok, den, 1.0)
        return np.stack([self.fx * x / den + self.cx, self.fy * y / den + self.cy], -1), ok

    def _unproject(self, uv):
        a, b = self.alpha, self.beta
        mx = (uv[..., 0] - self.cx) / self.fx
        my = (uv[..., 1] - self.cy) / self.fy
        r2 = mx * mx + my * my
        disc = 1 - (2 * a - 1) * b * r2
        ok = disc >= 0
        mz = (1 - b * a * a * r2) / (a * np.sqrt(np.maximum(disc, 0)) + 1 - a)
        rays = np.stack([mx, my, mz], -1)
        rays = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
        ok &= incidence(rays) < self.theta_max
        return rays, ok
