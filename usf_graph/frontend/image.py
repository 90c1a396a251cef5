"""SphericalImage: a spherical signal as a PyG graph."""

from __future__ import annotations

import torch
from torch_geometric.data import Data

from ..geometry import to_latlon


class SphericalImage(Data):
    r"""A signal on points of S2, as a :class:`torch_geometric.data.Data`.

    Attributes:
        x: ``[N, C]`` features (0 outside the field of view).
        pos: ``[N, 3]`` unit vectors in the sphere frame.
        mask: ``[N]`` bool, True where the camera sees the point.
        area: ``[N]`` quadrature weights (cell areas, summing to 4 pi for a full grid).
        edge_index: ``[2, E]`` radius edges (row 0 neighbour j, row 1 centre i).
        edge_weight: ``[E]`` geodesic distance of each edge in radians.

    Batches from PyG's ``DataLoader`` concatenate nodes and offset ``edge_index``.
    """

    @property
    def lat(self) -> torch.Tensor:
        """Latitude of each point in radians, [-pi/2, pi/2]."""
        return to_latlon(self.pos)[0]

    @property
    def lon(self) -> torch.Tensor:
        """Longitude of each point in radians, [-pi, pi)."""
        return to_latlon(self.pos)[1]
