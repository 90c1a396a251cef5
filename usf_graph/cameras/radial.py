"""Radial lens functions: a ray's incidence angle, and inverting a monotone function of it
(the radial distortions and fisheye mappings that have no closed-form inverse)."""

from __future__ import annotations

import numpy as np


def incidence(rays: np.ndarray) -> np.ndarray:
    """Angle between each ray and the optical axis +z, via atan2 (valid past 90 degrees)."""
    return np.arctan2(np.hypot(rays[..., 0], rays[..., 1]), rays[..., 2])


def azimuth(rays: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(cos, sin, ok)``: the unit direction in the image plane of each ray's azimuth, and
    whether the ray has a place in the image. A ray along the optical axis has no azimuth
    but lands on the centre (0, 0 here); one straight behind the lens (180 degrees) has
    none and lands nowhere: a lens that sees that far images it as a whole circle."""
    n = np.hypot(rays[..., 0], rays[..., 1])
    safe = np.where(n > 0, n, 1.0)
    return rays[..., 0] / safe, rays[..., 1] / safe, (n > 0) | (rays[..., 2] > 0)


def from_incidence(theta: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """Unit ray with incidence ``theta`` in the azimuth of the image vector (mx, my)."""
    r = np.hypot(mx, my)
    safe = np.where(r > 0, r, 1.0)
    s = np.sin(theta)
    return np.stack([np.where(r > 0, s * mx / safe, 0.0), np.where(r > 0, s * my / safe, 0.0),
                     np.cos(theta)], -1)


def monotone_limit(g, upper: float, n: int = 20001) -> float:
    """Largest t in (0, upper] such that g is strictly increasing on [0, t]."""
    t = np.linspace(0.0, upper, n)
    dg = np.diff(g(t))
    bad = np.nonzero(dg <= 0)[0]
    return float(upper if bad.size == 0 else t[bad[0]])


def _converged(step, t) -> np.ndarray:
    """A step of a few ulp: the iterate has reached float64 precision."""
    return ~np.isfinite(step) | (np.abs(step) <= 4e-16 * (1 + np.abs(t)))


def solve_monotone(g, dg, target: np.ndarray, hi: float, iters: int = 100, tol: float = 1e-13,
                   t0=None):
    """Solve g(t) = target for t in [0, hi], g increasing there (safeguarded Newton from
    ``t0``, default ``target``).

    Returns (t, converged). A target outside [g(0), g(hi)] or a point that does not
    converge comes back as not converged, never as a wrong answer. Each iteration works
    only on the points that are still moving, so a whole image costs a few passes.
    """
    target = np.asarray(target, np.float64)
    tgt = target.ravel()
    lo_t = np.zeros_like(tgt)
    hi_t = np.full_like(tgt, hi)
    inside = (tgt >= g(lo_t) - tol) & (tgt <= g(hi_t) + tol * (1 + np.abs(tgt)))
    start = tgt if t0 is None else np.broadcast_to(np.asarray(t0, np.float64), target.shape).ravel()
    t = np.clip(start, 0.0, hi) if hi > 0 else lo_t.copy()
    act = np.flatnonzero(np.isfinite(tgt))
    for _ in range(iters):
        if act.size == 0:
            break
        ta, lo, up = t[act], lo_t[act], hi_t[act]
        f = g(ta) - tgt[act]
        lo = np.where(f < 0, ta, lo)
        up = np.where(f > 0, ta, up)
        d = dg(ta)
        step = np.where(d > 0, ta - f / np.where(d > 0, d, 1.0), np.nan)
        tn = np.where((step > lo) & (step < up), step, 0.5 * (lo + up))
        tn = np.where(f == 0, ta, tn)  # a root: stay (bisecting would leave it)
        t[act], lo_t[act], hi_t[act] = tn, lo, up
        act = act[~_converged(tn - ta, ta)]
    t = t.reshape(target.shape)
    ok = inside.reshape(target.shape) & (np.abs(g(t) - target) <= tol * (1 + np.abs(target)))
    return t, ok
