"""The Grid type: sample points on S2 with cell areas, spacing and a coarsening step."""

from __future__ import annotations

import hashlib
import math
from collections import OrderedDict
from collections.abc import Callable

import numpy as np
import torch
from scipy.spatial import SphericalVoronoi, cKDTree

from ..geometry import chord_to_geodesic


def grid_size(what: str, value, lo: int, hi: float = math.inf) -> int:
    """``value`` as an int in [lo, hi]; a clear error for 2.5, -1 or "4"."""
    try:
        ok = int(value) == value and lo <= value <= hi
    except (TypeError, ValueError):
        ok = False
    if not ok:
        span = f"in [{lo}, {hi}]" if hi < math.inf else f">= {lo}"
        raise ValueError(f"{what} must be an integer {span}, got {value!r}")
    return int(value)


class Grid:
    """A set of unit vectors on S2.

    Attributes:
        pos: ``[N, 3]`` float64 unit vectors (torch).
        area: ``[N]`` float64 cell areas summing to 4*pi (computed on first use).
        spacing: mean nearest-neighbour geodesic distance in radians.
        name, params: what built it (``grids.from_spec(g.spec)`` rebuilds it).
    """

    def __init__(self, pos, name: str, params: dict, area=None,
                 coarsener: Callable[[], tuple[Grid, torch.Tensor]] | None = None):
        pos = torch.as_tensor(np.asarray(pos, np.float64))
        if pos.ndim != 2 or pos.shape[1] != 3 or pos.shape[0] < 4:
            raise ValueError(f"a grid needs [N >= 4, 3] points, got {tuple(pos.shape)}")
        self.pos = pos / pos.norm(dim=1, keepdim=True)
        self.name, self.params = name, dict(params)
        self._area = None if area is None else torch.as_tensor(np.asarray(area, np.float64))
        self._coarsener = coarsener
        self._spacing = None

    def __len__(self) -> int:
        return self.pos.shape[0]

    @property
    def num_points(self) -> int:
        """N, the number of points (``len(grid)``)."""
        return len(self)

    @property
    def spec(self) -> str:
        """A compact string such as ``icosahedral:5`` (see :func:`grids.from_spec`)."""
        return f"{self.name}:" + ",".join(str(v) for v in self.params.values())

    def key(self) -> dict:
        """What identifies the grid in cache keys: its name and parameters."""
        return {"grid": self.name, **self.params}

    @property
    def area(self) -> torch.Tensor:
        """Each point's area ``[N]`` (float64, steradians, summing to 4 pi): the given areas,
        else the spherical Voronoi cells' (computed on first use).
        """
        if self._area is None:
            self._area = torch.as_tensor(_kept_voronoi_areas(self.pos.numpy()))
        return self._area

    @property
    def spacing(self) -> float:
        """The mean geodesic distance from a point to its nearest neighbour, in radians."""
        if self._spacing is None:
            d, _ = cKDTree(self.pos.numpy()).query(self.pos.numpy(), k=2)
            self._spacing = float(chord_to_geodesic(d[:, 1]).mean())
        return self._spacing

    def coarsen(self) -> tuple[Grid, torch.Tensor]:
        """The next coarser grid and ``cluster [N]`` (index of each point's coarse point)."""
        if self._coarsener is None:
            raise ValueError(f"{self.spec} cannot be coarsened further")
        return self._coarsener()

    def hierarchy(self, levels: int) -> list[tuple[Grid, torch.Tensor]]:
        """``levels`` successive coarsenings: [(coarse_1, cluster_0->1), ...]."""
        out, g = [], self
        for _ in range(levels):
            g, cl = g.coarsen()
            out.append((g, cl))
        return out

    def quality(self) -> dict:
        """Uniformity figures (coefficients of variation, std / mean).

        ``area_cv``: the grid's own cells (HEALPix pixels, exact lat/lon cells, otherwise
        Voronoi); ``voronoi_area_cv``: spherical Voronoi cells of the points;
        ``nn_dist_cv``: nearest-neighbour distances; ``nbr6_dist_cv``: distances to the six
        nearest neighbours, which sees anisotropic neighbourhoods that the nearest misses.
        """
        vor = torch.as_tensor(voronoi_areas(self.pos.numpy()))
        d, _ = cKDTree(self.pos.numpy()).query(self.pos.numpy(), k=7)
        d = chord_to_geodesic(d[:, 1:])
        nn, nb = d[:, 0], d  # nearest neighbour; six nearest (a hexagonal neighbourhood)
        return {"grid": self.spec, "points": len(self),
                "area_cv": float(self.area.std() / self.area.mean()),
                "voronoi_area_cv": float(vor.std() / vor.mean()),
                "nn_dist_cv": float(nn.std() / nn.mean()),
                "nbr6_dist_cv": float(nb.std() / nb.mean()),
                "spacing_deg": math.degrees(float(nn.mean()))}

    def __repr__(self) -> str:
        return f"Grid({self.spec}, N={len(self)})"


def voronoi_areas(pos: np.ndarray) -> np.ndarray:
    """Areas of the spherical Voronoi cells of unit vectors ``pos`` (sum = 4*pi)."""
    sv = SphericalVoronoi(pos, radius=1.0, center=np.zeros(3))
    return sv.calculate_areas()


_AREAS: OrderedDict = OrderedDict()  # hash of the points -> their Voronoi areas (the last 16)


def _kept_voronoi_areas(pos: np.ndarray) -> np.ndarray:
    """:func:`voronoi_areas`, kept for the last 16 point sets by a hash of the points
    themselves: every ``grids.icosahedral(5)`` is a new object with the same points, and
    their diagram costs 50 ms at level 5 against well under 1 ms for the hash."""
    key = hashlib.sha256(np.ascontiguousarray(pos, np.float64).tobytes()).hexdigest()
    if key not in _AREAS:
        _AREAS[key] = voronoi_areas(pos)
        _AREAS[key].setflags(write=False)
        if len(_AREAS) > 16:
            _AREAS.popitem(last=False)
    _AREAS.move_to_end(key)
    return _AREAS[key].copy()


def nearest_cluster(fine: torch.Tensor, coarse: torch.Tensor) -> torch.Tensor:
    """Index of the nearest coarse point for each fine point (ties: lowest index)."""
    _, idx = cKDTree(coarse.numpy()).query(fine.numpy(), k=1)
    return torch.as_tensor(idx, dtype=torch.long)
