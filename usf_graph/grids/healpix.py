"""HEALPix pixel centres (Gorski et al. 2005) through healpy, the reference implementation."""

from __future__ import annotations

import math

import numpy as np
import torch

from .base import Grid, grid_size


def healpix(nside: int, nest: bool = True) -> Grid:
    """HEALPix grid: N = 12 * nside**2 equal-area pixels, centres in HEALPix order.

    ``nest=True`` gives the NESTED ordering, in which coarsening is ``idx // 4``;
    ``nest=False`` gives RING ordering (the clusters are mapped through NESTED).
    """
    import healpy as hp

    nside = grid_size("HEALPix nside", nside, 1)
    if nside & (nside - 1):
        raise ValueError(f"HEALPix nside must be a power of two >= 1, got {nside}")
    n = 12 * nside * nside
    pos = np.stack(hp.pix2vec(nside, np.arange(n), nest=nest), -1)

    def coarsen():
        coarse = healpix(nside // 2, nest)
        idx = np.arange(n)
        if nest:
            cl = idx // 4
        else:
            cl = hp.nest2ring(nside // 2, hp.ring2nest(nside, idx) // 4)
        return coarse, torch.as_tensor(cl, dtype=torch.long)

    return Grid(pos, "healpix", {"nside": nside, "nest": bool(nest)},
                area=np.full(n, 4 * math.pi / n), coarsener=coarsen if nside > 1 else None)


def locality_order(pos, nside: int = 2 ** 13) -> torch.Tensor:
    """A permutation numbering the points along HEALPix's nested (Z-order) curve, so that
    points close on the sphere sit close in memory. ``pos[order]`` (with the areas and
    signals permuted alike) lets :class:`~usf_graph.nn.SphericalConv` work in cache-sized
    tiles on large grids; HEALPix grids in nested order have this numbering already.
    Points sharing one of the ``12 nside^2`` pixels keep their relative order."""
    import healpy

    p = np.asarray(pos, np.float64)
    return torch.as_tensor(np.argsort(healpy.vec2pix(nside, *p.T, nest=True), kind="stable"))
