"""SphericalImage: a spherical signal as a PyG graph; and images' pixel values in [0, 1]."""

from __future__ import annotations

import numpy as np
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
        edge_attr: ``[E, 1]`` geodesic distance of each edge in radians (0 on self-loops),
            the layout of PyG's ``Distance`` transform; :attr:`edge_dist` is the same as
            ``[E]``.

    There is deliberately no ``edge_weight``: PyG layers such as ``GCNConv`` read
    ``edge_weight`` as an affinity (larger = closer), and radians would be silently
    wrong there. :class:`usf_graph.data.GaussianEdgeWeight` writes a true affinity, and
    :class:`usf_graph.data.VisibleSubgraph` drops the points the camera does not see,
    for layers that do not take a mask. Our convolutions take ``edge_attr`` directly:
    ``conv(img.x, img.edge_index, img.edge_attr, node_weight=img.area, mask=img.mask)``.

    Batches from PyG's ``DataLoader`` concatenate nodes and offset ``edge_index``. The class is
    a safe global for ``torch.load(..., weights_only=True)``, as PyG's ``Data`` is, so an
    ``InMemoryDataset`` of them saves and loads as safely as PyG's own.
    """

    @classmethod
    def on_grid(cls, x: torch.Tensor, grid, mask: torch.Tensor, edge_index: torch.Tensor,
                edge_weight: torch.Tensor) -> SphericalImage:
        """Values ``x [N, C]`` on ``grid`` with its radius graph (``edge_weight [E]``
        distances, stored as ``edge_attr [E, 1]``); geometry cast to ``x``'s dtype."""
        return cls(x=x, pos=grid.pos.to(x.dtype), mask=mask, area=grid.area.to(x.dtype),
                   edge_index=edge_index, edge_attr=edge_weight.to(x.dtype)[:, None])

    @property
    def edge_dist(self) -> torch.Tensor:
        """``[E]`` geodesic distance of each edge in radians (a view of ``edge_attr``)."""
        return self.edge_attr.view(-1)

    @property
    def lat(self) -> torch.Tensor:
        """Latitude of each point in radians, [-pi/2, pi/2]."""
        return to_latlon(self.pos)[0]

    @property
    def lon(self) -> torch.Tensor:
        """Longitude of each point in radians, [-pi, pi)."""
        return to_latlon(self.pos)[1]


# As PyG does for Data: its datasets and checkpoints load with torch.load(weights_only=True).
torch.serialization.add_safe_globals([SphericalImage])


def unit_range(image) -> np.ndarray:
    """Pixel values as float32 in [0, 1]: uint8 / 255, uint16 / 65535, float as it is
    (checked to lie in [0, 1]); other dtypes are refused."""
    a = np.asarray(image)
    if a.dtype == np.uint8 or a.dtype == np.uint16:
        return a.astype(np.float32) / np.iinfo(a.dtype).max
    if a.dtype.kind != "f":
        raise ValueError(f"image dtype {a.dtype} is not supported: give uint8, uint16 or "
                         "float in [0, 1]")
    a = a.astype(np.float32)
    seen = np.isfinite(a)
    if seen.any() and (a[seen].min() < 0 or a[seen].max() > 1):
        raise ValueError(f"a float image must hold values in [0, 1], got [{a[seen].min():g}, "
                         f"{a[seen].max():g}]; divide by 255 (or the sensor's maximum) first")
    return a


def to_uint8(image) -> np.ndarray:
    """Pixel values as uint8 for showing or drawing on: uint8 as it is, uint16 / 257 (its
    whole range, not its first 255), float in [0, 1] times 255 (clipped; NaN shown black);
    other dtypes are refused."""
    a = np.asarray(image)
    if a.dtype == np.uint8:
        return a
    if a.dtype == np.uint16:
        return np.round(a / 257.0).astype(np.uint8)
    if a.dtype.kind != "f":
        raise ValueError(f"image dtype {a.dtype} is not supported: give uint8, uint16 or "
                         "float in [0, 1]")
    return np.round(np.clip(np.nan_to_num(a.astype(np.float64)), 0, 1) * 255).astype(np.uint8)
