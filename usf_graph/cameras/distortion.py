"""OpenCV's pinhole distortion (radial rational, tangential, thin prism), both ways; used by
the pinhole and Mei models."""

from __future__ import annotations

import functools
import math

import numpy as np

from .radial import _converged, monotone_limit, solve_monotone


def _split_dist(dist) -> np.ndarray:
    d = np.zeros(12)
    if dist is not None:
        dist = np.asarray(dist, np.float64).ravel()
        if dist.size not in (0, 4, 5, 8, 12):
            raise ValueError(f"dist must have 4, 5, 8 or 12 coefficients in OpenCV order "
                             f"(k1,k2,p1,p2[,k3[,k4,k5,k6[,s1,s2,s3,s4]]]), got {dist.size}")
        d[:dist.size] = dist
    return d


def distort(d: np.ndarray, x: np.ndarray, y: np.ndarray, jacobian: bool = False):
    """OpenCV distortion of normalized coordinates; optionally with its 2x2 Jacobian."""
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = d
    r2 = x * x + y * y
    a = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    b = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    rad = a / b
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r2 * r2
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r2 * r2
    if not jacobian:
        return xd, yd
    da = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    db = k4 + r2 * (2 * k5 + 3 * k6 * r2)
    drad = (da * b - a * db) / (b * b)  # d rad / d r2
    j11 = rad + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x + 2 * s1 * x + 4 * s2 * r2 * x
    j12 = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y + 2 * s1 * y + 4 * s2 * r2 * y
    j21 = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y + 2 * s3 * x + 4 * s4 * r2 * x
    j22 = rad + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x + 2 * s3 * y + 4 * s4 * r2 * y
    return xd, yd, (j11, j12, j21, j22)


def distortion_radius_limit(d: np.ndarray, upper: float = 50.0) -> float:
    """Normalized radius of the disc on which the distortion is one-to-one: up to where the
    radial part r * rad(r^2) stops increasing and, with tangential or thin-prism terms, the
    2x2 Jacobian's determinant first reaches 0 (:func:`fold_radius`).

    Past it the distortion folds back, so pixels there have two preimages: the model's
    honest domain ends there. Remembered per coefficients: every copy of a camera
    (``with_rotation``, e.g. a random field of view per batch) would scan again.
    """
    return _radius_limit(tuple(float(v) for v in np.ravel(d)), float(upper))


@functools.lru_cache(maxsize=256)
def _radius_limit(coefficients: tuple, upper: float) -> float:
    d = np.array(coefficients)
    if not np.any(d):
        return math.inf
    radial = d.copy()
    radial[[2, 3, 8, 9, 10, 11]] = 0.0
    lim = monotone_limit(lambda t: distort(radial, t, np.zeros_like(t))[0], upper, 200001)
    if np.any(d[[2, 3, 8, 9, 10, 11]]):
        lim = min(lim, fold_radius(d, lim))
    return math.inf if lim >= upper else lim


def fold_radius(d: np.ndarray, upper: float, angles: int = 360, n: int = 1001) -> float:
    """Largest sampled radius r <= ``upper`` such that the distortion's Jacobian determinant
    is positive on the whole disc of radius r (scanned on ``angles`` rays of ``n`` radii,
    then again finely below the first fold found). Tangential terms can fold the map
    inside the radial part's monotone limit: there a pixel has two preimages."""
    phi = np.linspace(0.0, 2 * math.pi, angles, endpoint=False)[:, None]
    good, hi = 0.0, upper
    for _ in range(2):  # coarse, then fine between 0 and the first fold found
        r = np.linspace(0.0, hi, n)[None]
        _, _, (a, b, c, e) = distort(d, r * np.cos(phi), r * np.sin(phi), jacobian=True)
        bad = ~(a * e - b * c > 0)  # NaN counts as a fold
        if not bad.any():
            return hi
        first = int(np.where(bad.any(1), bad.argmax(1), n).min())
        if first == 0:
            return 0.0
        good, hi = float(r[0, first - 1]), float(r[0, first])
    return good


def undistort(d: np.ndarray, xd: np.ndarray, yd: np.ndarray, r_max: float,
              iters: int = 60, tol: float = 1e-14):
    """Invert :func:`distort` by damped Newton; returns (x, y, converged)."""
    x, y = xd.copy(), yd.copy()
    if not np.any(d):
        return x, y, np.isfinite(x) & np.isfinite(y)
    # Start from the exact inverse of the radial part (monotone up to r_max), then let
    # 2-D Newton absorb the tangential and thin-prism terms.
    radial = d.copy()
    radial[[2, 3, 8, 9, 10, 11]] = 0.0
    g = lambda t: distort(radial, t, np.zeros_like(t))[0]  # noqa: E731
    dg = lambda t: distort(radial, t, np.zeros_like(t), jacobian=True)[2][0]  # noqa: E731
    rd = np.hypot(xd, yd)
    r0, _ = solve_monotone(g, dg, rd, min(r_max, 1e4) * (1 - 1e-9))
    s0 = np.where(rd > 0, r0 / np.where(rd > 0, rd, 1), 1.0)
    x, y = (xd * s0).ravel(), (yd * s0).ravel()
    xdf, ydf = np.broadcast_to(xd, s0.shape).ravel(), np.broadcast_to(yd, s0.shape).ravel()
    act = np.arange(x.size)
    for _ in range(iters):  # Newton on the points still moving
        if act.size == 0:
            break
        xa, ya = x[act], y[act]
        fx, fy, (a, b, c, e) = distort(d, xa, ya, jacobian=True)
        rx, ry = fx - xdf[act], fy - ydf[act]
        det = a * e - b * c
        det = np.where(np.abs(det) > 1e-300, det, np.nan)
        dx = (e * rx - b * ry) / det
        dy = (a * ry - c * rx) / det
        # damp steps that would jump past the monotone radius
        scale = np.where(np.hypot(xa - dx, ya - dy) > r_max, 0.5, 1.0)
        x[act], y[act] = xa - scale * dx, ya - scale * dy
        act = act[~_converged(np.hypot(dx, dy), np.hypot(xa, ya))]
    x, y = x.reshape(s0.shape), y.reshape(s0.shape)
    fx, fy = distort(d, x, y)
    ok = (np.hypot(fx - xd, fy - yd) <= tol * (1 + np.hypot(xd, yd)) * 100) & (np.hypot(x, y) < r_max)
    return x, y, ok
