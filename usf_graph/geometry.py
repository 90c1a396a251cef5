"""S2 and SO(3) math in the design's sphere frame (x forward, y left, z up).

Every function accepts numpy arrays or torch tensors and returns the same kind.
Geometry is meant to be computed in float64.
"""

from __future__ import annotations

import math

import numpy as np
import torch

__all__ = [
    "to_latlon",
    "from_latlon",
    "normalize",
    "geodesic_distance",
    "tangent_towards",
    "chord_to_geodesic",
    "geodesic_to_chord",
    "random_rotation",
    "as_rotation_matrix",
    "rotation_from_axis_angle",
    "rotation_from_quaternion",
    "rotation_angle",
    "rotate",
    "level_rotation",
]


def _is_torch(x) -> bool:
    return isinstance(x, torch.Tensor)


def normalize(v, eps: float = 0.0):
    """Scale vectors ``v [..., 3]`` to unit length."""
    if _is_torch(v):
        return v / torch.linalg.norm(v, dim=-1, keepdim=True).clamp_min(eps or 1e-300)
    v = np.asarray(v, dtype=np.float64)
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), eps or 1e-300)


def to_latlon(p):
    """Unit vectors ``p [..., 3]`` -> (lat, lon): lat in [-pi/2, pi/2], lon in [-pi, pi)."""
    if _is_torch(p):
        x, y, z = p.unbind(-1)
        lat = torch.atan2(z, torch.sqrt(x * x + y * y))  # not hypot: ONNX has none
        lon = torch.atan2(y, x)
        lon = torch.where(lon >= math.pi, lon - 2 * math.pi, lon)
        return lat, lon
    p = np.asarray(p, dtype=np.float64)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    lat = np.arctan2(z, np.hypot(x, y))
    lon = np.arctan2(y, x)
    lon = np.where(lon >= np.pi, lon - 2 * np.pi, lon)
    return lat, lon


def from_latlon(lat, lon):
    """(lat, lon) in radians -> unit vectors ``[..., 3]`` (cos lat cos lon, cos lat sin lon, sin lat)."""
    if _is_torch(lat) or _is_torch(lon):
        lat, lon = torch.as_tensor(lat), torch.as_tensor(lon)
        c = torch.cos(lat)
        return torch.stack([c * torch.cos(lon), c * torch.sin(lon), torch.sin(lat)], -1)
    lat, lon = np.asarray(lat, np.float64), np.asarray(lon, np.float64)
    c = np.cos(lat)
    return np.stack([c * np.cos(lon), c * np.sin(lon), np.sin(lat)], -1)


def geodesic_distance(p, q):
    """Great-circle distance ``atan2(|p x q|, p . q)`` in radians.

    Inputs need not be unit length. Unlike the inverse cosine of p . q, it is accurate for tiny
    and near-antipodal distances, and its gradient stays finite at d = 0 and d = pi.
    """
    if _is_torch(p) or _is_torch(q):
        p, q = torch.as_tensor(p), torch.as_tensor(q)
        p, q = torch.broadcast_tensors(p, q)
        cross = torch.linalg.cross(p, q, dim=-1)
        return torch.atan2(torch.linalg.norm(cross, dim=-1), (p * q).sum(-1))
    p, q = np.asarray(p, np.float64), np.asarray(q, np.float64)
    cross = np.cross(p, q)
    return np.arctan2(np.linalg.norm(cross, axis=-1), (p * q).sum(-1))


def tangent_towards(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Unit tangents at unit vectors ``p [..., 3]`` pointing towards ``q [..., 3]`` (the log
    map's direction). Undefined where q = p (0 when the tangent vanishes exactly); callers
    mask those."""
    t = q - (q * p).sum(-1, keepdim=True) * p
    return t / t.norm(dim=-1, keepdim=True).clamp_min(1e-300)


def geodesic_to_chord(d):
    """Chord length ``2 sin(d/2)`` of a great-circle arc ``d``."""
    return 2 * (torch.sin(d / 2) if _is_torch(d) else np.sin(np.asarray(d) / 2))


def chord_to_geodesic(c):
    """Inverse of :func:`geodesic_to_chord` for c in [0, 2]."""
    if _is_torch(c):
        return 2 * torch.asin((c / 2).clamp(0, 1))
    return 2 * np.arcsin(np.clip(np.asarray(c) / 2, 0, 1))


def rotation_from_quaternion(q):
    """Unit quaternions ``q [..., 4]`` in (w, x, y, z) order -> rotation matrices ``[..., 3, 3]``.

    The quaternion is normalized first, so any non-zero 4-vector works.
    """
    q = normalize(q)
    if _is_torch(q):
        w, x, y, z = q.unbind(-1)
        stack = torch.stack
    else:
        w, x, y, z = (q[..., i] for i in range(4))
        stack = np.stack
    rows = [
        stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ]
    return stack(rows, -2)


def rotation_from_axis_angle(axis, angle):
    """Rotation by ``angle`` (radians, right hand) about ``axis [..., 3]`` (any length)."""
    if _is_torch(axis) or _is_torch(angle):
        axis = normalize(torch.as_tensor(axis, dtype=torch.float64))
        half = torch.as_tensor(angle, dtype=axis.dtype) / 2
        q = torch.cat([torch.cos(half)[..., None], torch.sin(half)[..., None] * axis], -1)
    else:
        axis = normalize(np.asarray(axis, np.float64))
        half = np.asarray(angle, np.float64) / 2
        q = np.concatenate([np.cos(half)[..., None], np.sin(half)[..., None] * axis], -1)
    return rotation_from_quaternion(q)


def as_rotation_matrix(R, name: str = "R") -> np.ndarray:
    """``R`` (numpy or a tensor) as a float64 ``[3, 3]`` array, refused unless it is a
    proper rotation: finite, orthonormal (``np.allclose(R R^T, I, atol=1e-6)``) and of
    determinant +1. A scaling or a reflection would otherwise move things without a word."""
    R = np.asarray(R.detach().cpu() if torch.is_tensor(R) else R, np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"{name} must be a 3x3 rotation matrix, got shape {R.shape}")
    if not np.isfinite(R).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    det = float(np.linalg.det(R))
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or det < 0:
        raise ValueError(f"{name} is not a rotation matrix (max |R R^T - I| = "
                         f"{float(np.abs(R @ R.T - np.eye(3)).max()):.2g}, det = {det:.3g}): "
                         "give a proper rotation matrix (orthonormal, det = +1), e.g. from "
                         "usf_graph.geometry.random_rotation or scipy's Rotation.as_matrix()")
    return R


def random_rotation(num: int | None = None, seed: int | None = None,
                    generator: torch.Generator | None = None,
                    dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Haar-uniform random rotations ``[3, 3]`` (or ``[num, 3, 3]``).

    A normalized 4-D Gaussian is uniform on S3, and S3 -> SO(3) maps the uniform measure
    to the Haar measure. Pass ``seed`` or a ``torch.Generator`` for reproducible draws.
    """
    if generator is None and seed is not None:
        generator = torch.Generator().manual_seed(int(seed))
    shape = (1 if num is None else int(num), 4)
    q = torch.randn(shape, generator=generator, dtype=torch.float64)
    R = rotation_from_quaternion(q).to(dtype)
    return R[0] if num is None else R


def rotation_angle(R):
    """Rotation angle in [0, pi] of ``R [..., 3, 3]``, via atan2 (stable near 0 and pi)."""
    if _is_torch(R):
        tr = R.diagonal(dim1=-2, dim2=-1).sum(-1)
        v = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                         R[..., 1, 0] - R[..., 0, 1]], -1)
        return torch.atan2(torch.linalg.norm(v, dim=-1), tr - 1)
    R = np.asarray(R, np.float64)
    tr = np.trace(R, axis1=-2, axis2=-1)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                  R[..., 1, 0] - R[..., 0, 1]], -1)
    return np.arctan2(np.linalg.norm(v, axis=-1), tr - 1)


def rotate(points, R):
    """Apply rotation(s) ``R [..., 3, 3]`` to points ``[..., N, 3]`` (or ``[N, 3]``): p' = R p."""
    if _is_torch(points) or _is_torch(R):
        points, R = torch.as_tensor(points), torch.as_tensor(R)
        return points @ R.to(points.dtype).transpose(-1, -2)
    return np.asarray(points) @ np.swapaxes(np.asarray(R, np.float64), -1, -2)


def level_rotation(up) -> np.ndarray:
    """The smallest rotation ``[3, 3]`` that turns the direction ``up [3]`` (any length) to
    +z: about the horizontal axis ``up x z``, orthogonal to both, so that it adds no turn
    about up (the heading stays). A frame turned by it is level; ``up = -z`` turns about x."""
    v = np.asarray(up, np.float64).reshape(-1)
    n = float(np.linalg.norm(v)) if v.shape == (3,) else 0.0
    if not (np.isfinite(n) and n > 0):
        raise ValueError(f"up must be a finite, non-zero 3-vector, got {np.asarray(up).tolist()}")
    u = v / n
    axis = np.cross(u, [0.0, 0.0, 1.0])
    s, c = float(np.linalg.norm(axis)), float(u[2])
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    return rotation_from_axis_angle(axis / s, math.atan2(s, c))
