"""HEALPix pixel centres (Gorski et al. 2005) through healpy, the reference implementation."""

from __future__ import annotations

import math

import numpy as np
import torch

from .base import Grid


def healpix(nside: int, nest: bool = True) -> Grid:
    """HEALPix grid: N = 12 * nside**2 equal-area pixels, centres in HEALPix order.

    ``nest=True`` gives the NESTED ordering, in which coarsening is ``idx // 4``;
    ``nest=False`` gives RING ordering (the clusters are mapped through NESTED).
    """
    import healpy as hp

    nside = int(nside)
    if nside < 1 or nside & (nside - 1):
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
