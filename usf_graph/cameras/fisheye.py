"""Fisheye lenses: the four classic projections, Kannala-Brandt (``cv2.fisheye``), the
field-of-view model and WoodScape's radial polynomial."""

from __future__ import annotations

import math

import numpy as np

from .base import (
    Camera,
    check_finite,
    check_positive,
    set_intrinsics,
)
from .radial import azimuth, from_incidence, incidence, monotone_limit, solve_monotone
from .resize import moved, one_factor

# r / f as a function of the incidence angle theta, its inverse, and the largest theta.
_PROJECTIONS = {
    "equidistant": (lambda t: t, lambda r: r, math.pi),
    "equisolid": (lambda t: 2 * np.sin(t / 2), lambda r: 2 * np.arcsin(np.clip(r / 2, 0, 1)), math.pi),
    "stereographic": (lambda t: 2 * np.tan(t / 2), lambda r: 2 * np.arctan(r / 2), math.pi),
    "orthographic": (lambda t: np.sin(t), lambda r: np.arcsin(np.clip(r, 0, 1)), math.pi / 2),
}


def _fov_limit(fov_deg, model_limit: float) -> float:
    if fov_deg is None:
        return model_limit
    fov = check_positive("fov_deg", fov_deg, "It is the full field of view in degrees.")
    if math.radians(fov) / 2 > model_limit + 1e-12:
        raise ValueError(f"fov_deg={fov} exceeds what this model can image "
                         f"({math.degrees(2 * model_limit):.1f} degrees); lower fov_deg.")
    return math.radians(fov) / 2


def _increasing_up_to(g, fov_deg, claim: str, name: str) -> float:
    """The largest incidence angle of a lens whose image radius ``g(theta)`` (``name``)
    increases up to there: its monotone limit, or ``fov_deg / 2`` where given and reached;
    a ``g`` that folds back before the claimed field of view raises (``claim``: the lens
    and what it is not)."""
    mono = monotone_limit(g, math.pi)
    claimed = _fov_limit(fov_deg, math.pi)
    if fov_deg is not None and mono < claimed - 1e-9:
        raise ValueError(f"{claim} over the claimed fov_deg={fov_deg}: {name} stops increasing at "
                         f"{math.degrees(2 * mono):.1f} degrees of field of view. Check the "
                         "coefficients or lower fov_deg.")
    return min(mono, claimed)


class Fisheye(Camera):
    """Ideal fisheye with radius ``r = f * g(theta)`` about the centre (cx, cy).

    ``model`` is equidistant (f theta), equisolid (2 f sin(theta/2)), stereographic
    (2 f tan(theta/2)) or orthographic (f sin theta, at most 90 degrees). ``fov_deg``
    optionally limits the lens to a field of view (the image circle).
    """

    def __init__(self, f, cx, cy, width, height, model="equidistant", fov_deg=None,
                 rotation=None):
        super().__init__(width, height, rotation)
        if model not in _PROJECTIONS:
            raise ValueError(f"unknown fisheye model {model!r}; use one of {sorted(_PROJECTIONS)}")
        self.f = check_positive("f", f, "The focal length is in pixels.")
        self.cx, self.cy = check_finite("cx", cx).item(), check_finite("cy", cy).item()
        self.projection, self.fov = model, fov_deg
        self._g, self._ginv, limit = _PROJECTIONS[model]
        self.theta_max = _fov_limit(fov_deg, limit)
        self.model = f"fisheye-{model}"

    def params(self) -> dict:
        return dict(f=self.f, cx=self.cx, cy=self.cy, width=self.width, height=self.height,
                    model=self.projection, fov_deg=self.fov)

    def _resized(self, width, height, sx, sy) -> Fisheye:
        s = one_factor(self, sx, sy)  # one focal length
        return Fisheye(self.f * s, float(moved(self.cx, s)), float(moved(self.cy, s)), width,
                       height, self.projection, self.fov, self.rotation)

    def _project(self, rays):
        theta = incidence(rays)
        r = self.f * self._g(theta)
        c, s, ok = azimuth(rays)
        uv = np.stack([self.cx + r * c, self.cy + r * s], -1)
        return uv, ok & (theta <= self.theta_max * (1 + 1e-12))

    def _unproject(self, uv):
        mx, my = uv[..., 0] - self.cx, uv[..., 1] - self.cy
        rn = np.hypot(mx, my) / self.f
        theta = self._ginv(rn)
        ok = (theta <= self.theta_max * (1 + 1e-12)) & (np.abs(self._g(theta) - rn) <= 1e-12 * (1 + rn))
        return from_incidence(theta, mx, my), ok


class KannalaBrandt(Camera):
    """Kannala-Brandt / OpenCV fisheye: theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8).

    Identical to ``cv2.fisheye`` for rays in front of the camera, but theta is computed
    with atan2, so lenses past 180 degrees work (OpenCV mirrors z <= 0 and clips at
    theta_d = pi/2). The valid domain is where theta_d(theta) is increasing, up to
    ``fov_deg / 2`` when given; a polynomial that folds back before that is rejected.
    """

    model = "kannala-brandt"

    def __init__(self, fx, fy, cx, cy, width, height, k=(0.0, 0.0, 0.0, 0.0), fov_deg=None,
                 rotation=None):
        super().__init__(width, height, rotation)
        set_intrinsics(self, fx, fy, cx, cy)
        self.k = check_finite("k", k)
        if self.k.shape != (4,):
            raise ValueError(f"k must hold the 4 coefficients k1..k4, got {self.k.tolist()}")
        self.fov = fov_deg
        self.theta_max = _increasing_up_to(self._theta_d, fov_deg,
                                           f"KannalaBrandt k={self.k.tolist()} is not monotonic",
                                           "theta_d")

    def _theta_d(self, t):
        t2 = t * t
        k1, k2, k3, k4 = self.k
        return t * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))

    def _dtheta_d(self, t):
        t2 = t * t
        k1, k2, k3, k4 = self.k
        return 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))

    def params(self) -> dict:
        return dict(fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy, width=self.width,
                    height=self.height, k=self.k.tolist(), fov_deg=self.fov)

    def _project(self, rays):
        theta = incidence(rays)
        td = self._theta_d(theta)
        c, s, ok = azimuth(rays)
        uv = np.stack([self.fx * td * c + self.cx, self.fy * td * s + self.cy], -1)
        return uv, ok & (theta <= self.theta_max * (1 + 1e-12))

    def _unproject(self, uv):
        mx = (uv[..., 0] - self.cx) / self.fx
        my = (uv[..., 1] - self.cy) / self.fy
        theta, ok = solve_monotone(self._theta_d, self._dtheta_d, np.hypot(mx, my), self.theta_max)
        return from_incidence(theta, mx, my), ok


class FOV(Camera):
    """Devernay and Faugeras' field-of-view model (COLMAP's FOV; PTAM's and DSO's ATAN):
    the pinhole's normalized radius r_u = tan(theta) is distorted to
    r_d = atan(2 r_u tan(omega / 2)) / omega, then u = fx r_d x / |(x, y)| + cx and
    likewise v. Closed form both ways; rays in front of the camera (theta < 90 degrees).
    ``omega`` in (0, pi) radians; omega -> 0 is the undistorted pinhole.
    """

    model = "fov"

    def __init__(self, fx, fy, cx, cy, width, height, omega, rotation=None):
        super().__init__(width, height, rotation)
        set_intrinsics(self, fx, fy, cx, cy)
        self.omega = check_positive("omega", omega, "It is the lens's field of view parameter "
                                    "in radians; a pinhole without distortion has none.")
        if self.omega >= math.pi:
            raise ValueError(f"FOV omega must lie in (0, pi) radians, got {self.omega}")
        self._t = 2 * math.tan(self.omega / 2)

    def params(self) -> dict:
        return dict(fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy, width=self.width,
                    height=self.height, omega=self.omega)

    def _project(self, rays):
        theta = incidence(rays)
        ok = theta < math.pi / 2
        rd = np.arctan(self._t * np.tan(np.where(ok, theta, 0.0))) / self.omega
        c, s, _ = azimuth(rays)  # nothing behind the lens: theta < 90 degrees
        return np.stack([self.fx * rd * c + self.cx, self.fy * rd * s + self.cy], -1), ok

    def _unproject(self, uv):
        mx = (uv[..., 0] - self.cx) / self.fx
        my = (uv[..., 1] - self.cy) / self.fy
        a = np.hypot(mx, my) * self.omega
        ok = a < math.pi / 2
        theta = np.arctan(np.tan(np.where(ok, a, 0.0)) / self._t)
        return from_incidence(theta, mx, my), ok


class RadialPoly(Camera):
    """WoodScape's fisheye (Valeo's ``radial_poly``): the image radius is a polynomial of
    the incidence angle in pixels, ``rho(theta) = k1 theta + k2 theta^2 + ... + kn
    theta^n``, and ``u = cx + rho x / |(x, y)|``, ``v = cy + a rho y / |(x, y)|`` with the
    aspect ratio ``a``. Unlike Kannala-Brandt the polynomial has even powers too. Its
    inverse is found by Newton's method where ``rho`` increases, up to ``fov_deg / 2``
    when given. :func:`usf_graph.cameras.load` reads WoodScape's calibration JSON into it.
    """

    model = "radial-poly"

    def __init__(self, k, cx, cy, width, height, aspect_ratio=1.0, fov_deg=None, rotation=None):
        super().__init__(width, height, rotation)
        self.k = check_finite("k", k).ravel()
        if self.k.size < 1 or not self.k[0] > 0:
            raise ValueError(f"RadialPoly needs k1 > 0 (pixels per radian at the centre), got "
                             f"k={self.k.tolist()}")
        self.cx, self.cy = check_finite("cx", cx).item(), check_finite("cy", cy).item()
        self.aspect_ratio = check_positive("aspect_ratio", aspect_ratio,
                                           "It is the vertical over the horizontal pixel scale.")
        self.fov = fov_deg
        self.theta_max = _increasing_up_to(self._rho, fov_deg,
                                           f"RadialPoly k={self.k.tolist()} is not increasing", "rho")

    def _rho(self, t):
        """``rho(theta)`` by Horner's rule."""
        t = np.asarray(t, np.float64)
        acc = np.zeros_like(t)
        for c in self.k[::-1]:
            acc = (acc + c) * t
        return acc

    def _drho(self, t):
        t = np.asarray(t, np.float64)
        acc = np.zeros_like(t)
        for n in range(self.k.size, 0, -1):
            acc = acc * t + n * self.k[n - 1]
        return acc

    def params(self) -> dict:
        return dict(k=self.k.tolist(), cx=self.cx, cy=self.cy, width=self.width,
                    height=self.height, aspect_ratio=self.aspect_ratio, fov_deg=self.fov)

    def _resized(self, width, height, sx, sy) -> RadialPoly:
        return RadialPoly(self.k * sx, float(moved(self.cx, sx)), float(moved(self.cy, sy)),
                          width, height, self.aspect_ratio * sy / sx, self.fov, self.rotation)

    def _project(self, rays):
        theta = incidence(rays)
        rho = self._rho(theta)
        c, s, ok = azimuth(rays)
        uv = np.stack([self.cx + rho * c, self.cy + self.aspect_ratio * rho * s], -1)
        return uv, ok & (theta <= self.theta_max * (1 + 1e-12))

    def _unproject(self, uv):
        mx, my = uv[..., 0] - self.cx, (uv[..., 1] - self.cy) / self.aspect_ratio
        theta, ok = solve_monotone(self._rho, self._drho, np.hypot(mx, my), self.theta_max,
                                   t0=np.hypot(mx, my) / self.k[0])
        return from_incidence(theta, mx, my), ok
