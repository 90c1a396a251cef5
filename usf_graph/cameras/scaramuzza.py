"""Scaramuzza's OCamCalib model: a polynomial in the sensor radius, with an affine part."""

from __future__ import annotations

import numpy as np

from .base import Camera, check_finite
from .radial import azimuth, incidence, monotone_limit, solve_monotone
from .resize import moved, one_factor


class Scaramuzza(Camera):
    """OCamCalib camera (``calib_results.txt``).

    ``pol`` = (a0, a1, ...) with a0 < 0, ``center`` = (row, column) = (xc, yc) and the
    affine matrix [[c, d], [e, 1]] act on (row, column) exactly as OCamCalib's
    ``cam2world``. OCamCalib's frame (x down the rows, y along the columns, the scene at
    -z) is turned into the OpenCV optical frame. ``project`` inverts the polynomial with a
    safeguarded Newton solve (``invpol`` is only a fitted approximation and is kept for
    reference). The valid domain ends at the image corners or where the incidence angle
    stops increasing with the radius.
    """

    model = "scaramuzza"

    def __init__(self, pol, center, affine, width, height, invpol=None, rotation=None):
        super().__init__(width, height, rotation)
        self.pol = check_finite("pol", pol)
        if self.pol.ndim != 1 or self.pol.size < 2 or self.pol[0] >= 0:
            raise ValueError(f"OCamCalib pol must list a0, a1, ... with a0 < 0, got {self.pol.tolist()}")
        self.center = check_finite("center", center)
        self.affine = check_finite("affine", affine)
        if self.center.shape != (2,) or self.affine.shape != (3,):
            raise ValueError("center must be (row, column) and affine must be (c, d, e)")
        c, d, e = self.affine
        if abs(c - d * e) < 1e-12:
            raise ValueError(f"affine (c, d, e)={self.affine.tolist()} is singular: c - d*e = 0")
        self.invpol = None if invpol is None else check_finite("invpol", invpol)
        corners = np.array([[0, 0], [self.width - 1, 0], [0, self.height - 1],
                            [self.width - 1, self.height - 1]], np.float64)
        rho_img = np.hypot(*self._sensor(corners)).max() * 1.02
        self.rho_max = monotone_limit(self._theta, rho_img)

    def params(self) -> dict:
        return dict(pol=self.pol.tolist(), center=self.center.tolist(),
                    affine=self.affine.tolist(), width=self.width, height=self.height,
                    invpol=None if self.invpol is None else self.invpol.tolist())

    def _resized(self, width, height, sx, sy) -> Scaramuzza:
        # the sensor radius scales by s: pol'(s r) = s pol(r), and so does invpol's rho
        s = one_factor(self, sx, sy)
        return Scaramuzza([a * s ** (1 - i) for i, a in enumerate(self.pol)],
                          moved(self.center, s), self.affine, width, height,
                          None if self.invpol is None else self.invpol * s, self.rotation)

    def _theta(self, rho):  # incidence angle as a function of the sensor radius
        return np.arctan2(rho, -np.polynomial.polynomial.polyval(rho, self.pol))

    def _dtheta(self, rho):
        z = np.polynomial.polynomial.polyval(rho, self.pol)
        dz = np.polynomial.polynomial.polyval(rho, np.polynomial.polynomial.polyder(self.pol))
        return (-z + rho * dz) / (rho * rho + z * z)

    def _sensor(self, uv):
        c, d, e = self.affine
        dr, dc = uv[..., 1] - self.center[0], uv[..., 0] - self.center[1]
        inv = 1.0 / (c - d * e)
        return inv * (dr - d * dc), inv * (-e * dr + c * dc)

    def _unproject(self, uv):
        xp, yp = self._sensor(uv)
        rho = np.hypot(xp, yp)
        z = np.polynomial.polynomial.polyval(rho, self.pol)
        rays = np.stack([yp, xp, -z], -1)  # OCamCalib (x=row, y=col, -z) -> OpenCV
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True), rho <= self.rho_max

    def _project(self, rays):
        theta = incidence(rays)
        rho, ok = solve_monotone(self._theta, self._dtheta, theta, self.rho_max,
                                 t0=theta * (self.rho_max / self._theta(self.rho_max)))
        cos, sin, seen = azimuth(rays)
        xp, yp = rho * sin, rho * cos
        c, d, e = self.affine
        row = c * xp + d * yp + self.center[0]
        col = e * xp + yp + self.center[1]
        return np.stack([col, row], -1), ok & seen
