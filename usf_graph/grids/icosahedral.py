"""Icosahedral (geodesic) grid by recursive edge subdivision."""

from __future__ import annotations

import functools
import math

import numpy as np
import torch

from .base import Grid, grid_size, nearest_cluster


def _icosahedron():
    t = (1 + math.sqrt(5)) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]],
                 np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                  [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                  [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                  [8, 6, 7], [9, 8, 1]])
    return v / np.linalg.norm(v, axis=1, keepdims=True), f


@functools.lru_cache(maxsize=16)
def _mesh(level: int):
    if level == 0:
        return _icosahedron()
    v, f = _mesh(level - 1)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    edges, inv = np.unique(e, axis=0, return_inverse=True)
    mid = v[edges[:, 0]] + v[edges[:, 1]]
    mid /= np.linalg.norm(mid, axis=1, keepdims=True)
    m = len(v) + inv.reshape(3, -1)  # new vertex index of edges (01, 12, 20) per face
    a, b, c = f.T
    faces = np.concatenate([np.stack([a, m[0], m[2]], 1), np.stack([b, m[1], m[0]], 1),
                            np.stack([c, m[2], m[1]], 1), np.stack([m[0], m[1], m[2]], 1)])
    return np.concatenate([v, mid]), faces


def icosahedral(level: int) -> Grid:
    """Vertices of the subdivided icosahedron: N = 10 * 4**level + 2.

    Nested: the first N(level - 1) points are exactly the grid of ``level - 1``. Each new
    vertex is the normalized midpoint of an edge of the previous level. Coarsening
    assigns every point to its nearest vertex of the previous level.
    """
    level = grid_size("icosahedral level", level, 0, 10)
    v, _ = _mesh(level)

    def coarsen():
        coarse = icosahedral(level - 1)
        return coarse, nearest_cluster(torch.as_tensor(v), coarse.pos)

    return Grid(v, "icosahedral", {"level": level}, coarsener=coarsen if level > 0 else None)


def icosahedral_faces(level: int) -> np.ndarray:
    """Triangles ``[F, 3]`` of the level's mesh (for plots and interpolation)."""
    return _mesh(int(level))[1]
