"""Fibonacci (golden spiral) and equiangular (latitude/longitude) grids."""

from __future__ import annotations

import math

import numpy as np
import torch

from ..geometry import from_latlon
from .base import Grid, grid_size, nearest_cluster


def fibonacci(n: int) -> Grid:
    """``n`` points on a golden-angle spiral: z_i = 1 - (2i + 1)/n, lon_i = i * golden angle."""
    n = grid_size("a Fibonacci grid's point count n", n, 4)
    i = np.arange(n, dtype=np.float64)
    z = 1 - (2 * i + 1) / n
    lon = np.mod(i * math.pi * (3 - math.sqrt(5)), 2 * math.pi)
    r = np.sqrt(1 - z * z)
    pos = np.stack([r * np.cos(lon), r * np.sin(lon), z], -1)

    def coarsen():
        coarse = fibonacci(n // 4)
        return coarse, nearest_cluster(torch.as_tensor(pos), coarse.pos)

    return Grid(pos, "fibonacci", {"n": n}, coarsener=coarsen if n // 4 >= 4 else None)


def equiangular(nlat: int, nlon: int) -> Grid:
    """Cell centres of an nlat x nlon latitude/longitude grid, row-major from the north
    and, in a row, from left to right as seen from the centre (longitude decreasing).

    Point ``i * nlon + j`` is pixel (row i, column j) of an equirectangular image of the
    same size (DESIGN.md's pixel convention), so ``signal.reshape(nlat, nlon, -1)`` is that
    image, the right way round. The cell areas are exact.
    """
    nlat, nlon = grid_size("equiangular nlat", nlat, 2), grid_size("equiangular nlon", nlon, 2)
    lat = math.pi / 2 - math.pi * (np.arange(nlat) + 0.5) / nlat
    lon = math.pi - 2 * math.pi * (np.arange(nlon) + 0.5) / nlon
    pos = from_latlon(*np.meshgrid(lat, lon, indexing="ij")).reshape(-1, 3)
    edges = math.pi / 2 - math.pi * np.arange(nlat + 1) / nlat
    band = (np.sin(edges[:-1]) - np.sin(edges[1:])) * 2 * math.pi / nlon
    area = np.repeat(band, nlon)

    def coarsen():
        coarse = equiangular(nlat // 2, nlon // 2)
        return coarse, nearest_cluster(torch.as_tensor(pos), coarse.pos)

    ok = nlat // 2 >= 2 and nlon // 2 >= 2
    return Grid(pos, "equiangular", {"nlat": nlat, "nlon": nlon}, area=area,
                coarsener=coarsen if ok else None)
