r"""Spherical boxes: the region of S2 bounded by four great circles.

A box is ``[lon, lat, fov_x, fov_y, roll]`` in radians, in the sphere frame of DESIGN.md
(x forward, y left, z up; longitude counter-clockwise from +x). Its centre direction is
:math:`c`; its horizontal axis :math:`e` is the local east at :math:`c` turned by ``roll``
towards the local north :math:`n`. A direction :math:`p` is inside when

.. math::
    p \cdot c > 0,\quad |p \cdot e| \le \tan(f_x/2)\, p \cdot c,\quad
    |p \cdot n| \le \tan(f_y/2)\, p \cdot c,

the tangent-plane rectangle at :math:`c` seen from the sphere's centre. Files use PANDORA's
``[lon, lat, fov_x, fov_y, gamma]`` in degrees, where longitude grows to the right of the
panorama and positive gamma turns the box counter-clockwise as displayed: both are the
negatives of ours (:func:`from_pandora`, :func:`to_pandora`).
"""

from __future__ import annotations

import numpy as np
import torch

from ..geometry import (
    as_rotation_matrix,
    from_latlon,
    level_rotation,
    normalize,
    to_latlon,
)
from ..tracing import check_values

__all__ = ["box_axes", "box_planes", "boxes_from_axes", "canonical_boxes", "from_pandora", "to_pandora",
           "points_in_boxes", "share_in_view", "rotate_boxes", "fit_box", "box_corners", "box_edges"]


def _as_boxes(boxes):
    """Boxes as float64 numpy, or tensors as they are; shape and finiteness checked (the
    values not while exporting: :func:`~usf_graph.tracing.check_values`)."""
    b = boxes if torch.is_tensor(boxes) else np.asarray(boxes, np.float64)
    if tuple(b.shape[-1:]) != (5,):
        raise ValueError(f"boxes must have shape [..., 5] (lon, lat, fov_x, fov_y, roll), got {tuple(b.shape)}")
    if check_values() and not bool((torch.isfinite(b) if torch.is_tensor(b) else np.isfinite(b)).all()):
        raise ValueError("boxes contain NaN or infinite values")
    return b


def _local_frame(lon, lat):
    """East and north unit vectors at (lon, lat); at a pole east is the limit along ``lon``."""
    xp = torch if torch.is_tensor(lon) else np
    e0 = xp.stack([-xp.sin(lon), xp.cos(lon), xp.zeros_like(lon)], -1)
    n0 = xp.stack([-xp.sin(lat) * xp.cos(lon), -xp.sin(lat) * xp.sin(lon), xp.cos(lat)], -1)
    return e0, n0


def box_axes(boxes):
    """Boxes ``[..., 5]`` (numpy or torch) -> centre ``c``, horizontal axis ``e`` and
    vertical axis ``n``, each ``[..., 3]`` (a right-handed frame ``(c, e, n)``)."""
    b = _as_boxes(boxes)
    xp = torch if torch.is_tensor(b) else np
    lon, lat, roll = b[..., 0], b[..., 1], b[..., 4]
    c = from_latlon(lat, lon)
    e0, n0 = _local_frame(lon, lat)
    cr, sr = xp.cos(roll)[..., None], xp.sin(roll)[..., None]
    return c, cr * e0 + sr * n0, cr * n0 - sr * e0


def box_planes(boxes):
    """Boxes ``[..., 5]`` -> the inward normals ``[..., 4, 3]`` of their four great circles
    (inside: ``p . m >= 0`` for all four) and their corners ``[..., 4, 3]`` in order around
    the box. Both stay finite up to fields of view of 180 degrees."""
    b = _as_boxes(boxes)
    xp = torch if torch.is_tensor(b) else np
    c, e, n = box_axes(b)
    hx, hy = b[..., 2:3] / 2, b[..., 3:4] / 2
    sx, cx, sy, cy = xp.sin(hx), xp.cos(hx), xp.sin(hy), xp.cos(hy)
    planes = xp.stack([sx * c - cx * e, sx * c + cx * e, sy * c - cy * n, sy * c + cy * n], -2)
    base = cx * cy * c
    corners = xp.stack([base + sx * cy * e + cx * sy * n, base + sx * cy * e - cx * sy * n,
                        base - sx * cy * e - cx * sy * n, base - sx * cy * e + cx * sy * n], -2)
    return planes, corners / (corners * corners).sum(-1, keepdims=True) ** 0.5


def boxes_from_axes(c, e, fov_x, fov_y):
    """The boxes with centre ``c [..., 3]``, horizontal axis ``e`` (of any length; only its
    part in the tangent plane at ``c`` counts) and fields of view (radians); roll in
    [-pi/2, pi/2). Numpy in, float64 numpy out; tensors in, tensors of their dtype out
    (traceable)."""
    xp = torch if torch.is_tensor(c) else np
    if xp is np:
        c, e = np.asarray(c, np.float64), np.asarray(e, np.float64)
    c = normalize(c)
    lat, lon = to_latlon(c)
    e0, n0 = _local_frame(lon, lat)  # tangent at c: e's normal part drops out of the roll
    roll = xp.arctan2((e * n0).sum(-1), (e * e0).sum(-1))
    roll = xp.remainder(roll + np.pi / 2, np.pi) - np.pi / 2  # a half turn maps a box onto itself
    if xp is torch:
        fx, fy = torch.as_tensor(fov_x, dtype=c.dtype), torch.as_tensor(fov_y, dtype=c.dtype)
        return torch.stack(torch.broadcast_tensors(lon, lat, fx, fy, roll), -1)
    fx, fy = np.broadcast_arrays(np.asarray(fov_x, np.float64), np.asarray(fov_y, np.float64))
    return np.stack(np.broadcast_arrays(lon, lat, fx, fy, roll), -1)


def from_pandora(bbox):
    """PANDORA ``[lon, lat, fov_x, fov_y, gamma]`` (degrees, image terms) -> our boxes."""
    b = np.radians(_as_boxes(bbox))
    b[..., 0] *= -1
    b[..., 4] *= -1
    b[..., 0] = np.mod(b[..., 0] + np.pi, 2 * np.pi) - np.pi
    return b


def to_pandora(boxes):
    """Our boxes -> PANDORA ``[lon, lat, fov_x, fov_y, gamma]`` in degrees, gamma wrapped to
    [-90, 90] (a half turn of a box is the same box)."""
    b = _as_boxes(boxes).copy()
    b[..., 0] *= -1
    b[..., 4] = -(np.mod(b[..., 4] + np.pi / 2, np.pi) - np.pi / 2)
    b[..., 0] = np.mod(b[..., 0] + np.pi, 2 * np.pi) - np.pi
    return np.degrees(b)


def canonical_boxes(boxes):
    """The same boxes with ``|roll| <= pi/4``: a box turned a quarter turn further with its
    two fields of view swapped covers the same directions, and the detectors' roll is
    only known modulo a quarter turn, so their boxes may come in either form."""
    b = _as_boxes(boxes).copy()
    roll = np.mod(b[..., 4] + np.pi / 2, np.pi) - np.pi / 2  # a half turn is the same box
    swap = np.abs(roll) > np.pi / 4
    b[..., 4] = np.where(swap, roll - np.sign(roll) * np.pi / 2, roll)
    b[..., 2], b[..., 3] = np.where(swap, b[..., 3], b[..., 2]), np.where(swap, b[..., 2], b[..., 3])
    return b


def points_in_boxes(points, boxes, margin: float = 0.0) -> np.ndarray:
    """``[P, B]`` True where direction ``points[p]`` lies in ``boxes[b]``; ``margin``
    (radians) widens each side's half field of view (negative shrinks it). A field of view
    of 180 degrees or more holds the whole front half of the sphere across it: the
    tangent plane has no edge there."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if not np.isfinite(p).all():
        raise ValueError("points contain NaN or infinite values")
    b = np.asarray(_as_boxes(boxes), np.float64).reshape(-1, 5)
    c, e, n = box_axes(b)
    z, x, y = p @ c.T, p @ e.T, p @ n.T
    hx = np.tan(np.clip(b[:, 2] / 2 + margin, 0, np.pi / 2))
    hy = np.tan(np.clip(b[:, 3] / 2 + margin, 0, np.pi / 2))
    eps = 1e-12 * np.abs(z)
    return (z > 0) & (np.abs(x) <= hx * z + eps) & (np.abs(y) <= hy * z + eps)


def share_in_view(boxes, sees, n: int = 64) -> np.ndarray:
    r"""The share of each box's solid angle that a field of view covers, ``[B]`` in [0, 1].

    ``sees`` maps directions ``[P, 3]`` (in the boxes' frame) to bool ``[P]``: for a
    camera, ``lambda d: camera.sees(d)[1]``. The box is sampled at the midpoints of an
    ``n x n`` grid of angles :math:`(\alpha, \beta)` across its tangent plane, each
    weighted by its solid angle :math:`d\Omega = \sec^2\alpha \sec^2\beta\, (1 +
    \tan^2\alpha + \tan^2\beta)^{-3/2}\, d\alpha\, d\beta`, so the share is exact but for
    the border of the field of view, resolved to ``fov / n``."""
    b = np.asarray(_as_boxes(boxes), np.float64).reshape(-1, 5)
    t = (np.arange(n) + 0.5) / n - 0.5
    out = np.zeros(len(b))
    for s in range(0, len(b), 256):  # about 25 MB of directions at a time
        c, e, m = box_axes(b[s:s + 256])
        u, v = np.tan(t * b[s:s + 256, 2:3]), np.tan(t * b[s:s + 256, 3:4])  # [K, n]
        r2 = 1 + u[:, :, None] ** 2 + v[:, None, :] ** 2
        w = (1 + u ** 2)[:, :, None] * (1 + v ** 2)[:, None, :] / r2 ** 1.5
        d = (c[:, None, None] + u[:, :, None, None] * e[:, None, None]
             + v[:, None, :, None] * m[:, None, None]) / np.sqrt(r2)[..., None]
        seen = np.asarray(sees(d.reshape(-1, 3)), bool).reshape(w.shape)
        out[s:s + 256] = (w * seen).sum((1, 2)) / w.sum((1, 2))
    return out


def rotate_boxes(boxes, R):
    """The boxes seen in a frame rotated by ``R`` (``R @ p`` maps old directions to new):
    exact, since a rotation maps great circles to great circles. Boxes and ``R`` as numpy
    or CPU tensors; returns float64 numpy."""
    b = np.asarray(_as_boxes(boxes), np.float64)
    R = as_rotation_matrix(R)
    c, e, _ = box_axes(b)
    return boxes_from_axes(c @ R.T, e @ R.T, b[..., 2], b[..., 3])


def box_corners(boxes):
    """The four corner directions ``[..., 4, 3]`` of each box, in order around it: (+e, +n),
    (+e, -n), (-e, -n), (-e, +n) in its own axes."""
    return box_planes(boxes)[1]


def box_edges(boxes, n: int = 32):
    """Points along the four great-circle edges, ``[..., 4 * n + 1, 3]`` (closed), for drawing."""
    k = box_corners(boxes)
    t = np.linspace(0, 1, n, endpoint=False)[:, None]
    sides = [normalize(k[..., i, None, :] * (1 - t) + k[..., (i + 1) % 4, None, :] * t)
             for i in range(4)]
    return np.concatenate(sides + [k[..., :1, :]], -2)


def _gnomonic(p, c, e, n):
    z = p @ c
    return p @ e / z, p @ n / z, z


def fit_box(directions, up=(0.0, 0.0, 1.0), iters: int = 60, tol: float = 1e-12, centre=None):
    """The tight box around unit ``directions [M, 3]`` whose vertical axis points towards
    ``up`` (roll 0 when ``up`` is the frame's z axis).

    The centre is moved until the directions' gnomonic extents are symmetric about it; only
    their convex hull matters, since great circles are lines in the gnomonic plane. Returns
    ``None`` when the directions do not fit in an open hemisphere (the object surrounds the
    viewpoint). ``centre`` is a starting guess (the mean direction by default).

    Around ``up`` itself, and around ``-up``, the answer is not unique: a box that contains
    either pole has roll 0 about a frame that turns with its centre, so several centres can
    give symmetric extents, and the fit may return another tight up-aligned box (within
    about 1% of the area in tests, axes possibly swapped), or converge slowly to the same
    one (about 3e-7 rad in tests).
    """
    from scipy.spatial import ConvexHull, QhullError

    d = normalize(np.asarray(directions, np.float64).reshape(-1, 3))
    if len(d) == 0:
        raise ValueError("fit_box needs at least one direction")
    up = normalize(np.asarray(up, np.float64))
    R = level_rotation(up)  # work in a frame whose z is up, so roll 0 = vertical axis up
    d = d @ R.T
    c = normalize(d.mean(0) if centre is None else R @ np.asarray(centre, np.float64))
    if not np.all(d @ c > 1e-6):
        return None
    if len(d) > 8:  # keep the hull vertices in the gnomonic plane at c
        e0, n0 = _local_frame(*to_latlon(c)[::-1])
        x, y, _ = _gnomonic(d, c, e0, n0)
        try:
            d = d[ConvexHull(np.stack([x, y], -1)).vertices]
        except QhullError:  # collinear or a single point: extremes are enough
            d = d[np.unique([x.argmin(), x.argmax(), y.argmin(), y.argmax()])]
    lat, lon = to_latlon(c)
    t, r = np.array([lon, lat]), _asymmetry(d, lon, lat)
    for _ in range(iters):  # Newton on (lon, lat), Jacobian by differences, with backtracking
        if r is None or np.abs(r).max() < tol:
            break
        probe = [_asymmetry(d, *(t + 1e-7 * np.eye(2)[k])) for k in range(2)]
        if any(q is None for q in probe):
            break
        J = np.stack([(q - r) / 1e-7 for q in probe], -1)
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        for scale in 0.5 ** np.arange(30):
            r_new = _asymmetry(d, *(t + scale * step))
            if r_new is not None and np.abs(r_new).max() < np.abs(r).max():
                t, r = t + scale * step, r_new
                break
        else:
            break
    if r is None:
        return None
    lon, lat = t
    e0, n0 = _local_frame(lon, lat)
    x, y, _ = _gnomonic(d, from_latlon(lat, lon), e0, n0)
    fx, fy = 2 * np.arctan(np.abs(x).max()), 2 * np.arctan(np.abs(y).max())
    lon = np.mod(lon + np.pi, 2 * np.pi) - np.pi
    return rotate_boxes(np.array([lon, lat, fx, fy, 0.0]), R.T)


def _asymmetry(d, lon, lat):
    """Midpoints of the gnomonic extents of ``d`` at (lon, lat), or None past the horizon."""
    e0, n0 = _local_frame(lon, lat)
    x, y, z = _gnomonic(d, from_latlon(lat, lon), e0, n0)
    if not np.all(z > 1e-9):
        return None
    return np.array([(x.max() + x.min()) / 2, (y.max() + y.min()) / 2])
