"""PyG transforms for spherical samples: random rotations, radius graphs, and the bridges to
PyG's own layers (an affinity ``edge_weight``, the visible subgraph)."""

from __future__ import annotations

import torch
from torch_geometric.data import Data
from torch_geometric.transforms import BaseTransform

from ..frontend import GeometryCache, SphericalFrontend
from ..frontend.interpolation import barycentric_entries
from ..geometry import level_rotation, random_rotation
from ..graph import geodesic_radius_graph


class RandomRotation(BaseTransform):
    r"""Rotates a spherical sample by a Haar-uniform random rotation :math:`R \in SO(3)`.

    The rotated signal is :math:`x'(p) = x(R^\top p)`: the scene turns by :math:`R`.

    * With ``frontend`` given and the source picture stored on the sample as
      ``data.image``, the picture is re-lifted through the camera mounted with
      :math:`R` (``camera.turned(R)``, its position turned too). This is exact: the
      grid samples the rotated continuous signal directly.
    * Otherwise the signal is resampled grid to grid with barycentric weights on the
      grid's triangulation; a point stays visible only if its whole triangle is.

    Per-point labels ``y`` and gravity ``up`` turn with the signal (:func:`rotate_sample`);
    a sample with spherical boxes is refused. The rotation used is stored in
    ``data.rotation [3, 3]``.

    Args:
        seed: seed of a private ``torch.Generator``; the sequence of rotations is then
            reproducible. ``generator`` may be passed instead.
        frontend: the :class:`~usf_graph.frontend.SphericalFrontend` that lifted the
            samples, for the exact path.
    """

    def __init__(self, seed: int | None = None, generator: torch.Generator | None = None,
                 frontend=None):
        if generator is None:
            generator = torch.Generator()
            generator.manual_seed(int(seed)) if seed is not None else generator.seed()
        self.generator, self.frontend = generator, frontend

    def forward(self, data: Data) -> Data:
        """Rotates ``data`` by a new random rotation, kept in ``data.rotation`` [3, 3]."""
        R = random_rotation(generator=self.generator)
        data = rotate_sample(data, R, self.frontend)
        data.rotation = R.to(data.pos.dtype)
        return data

    def __repr__(self) -> str:
        exact = "re-lift" if self.frontend is not None else "grid-to-grid"
        return f"{type(self).__name__}({exact})"


class Level(BaseTransform):
    r"""Turns a sample so that its gravity ``data.up`` (e.g. from an IMU:
    :class:`~usf_graph.datasets.RosBagFrames`) becomes +z: by the smallest rotation
    :math:`R` with :math:`R\,u = e_z` (:func:`~usf_graph.geometry.level_rotation`, which
    keeps the heading), applied as :class:`RandomRotation` applies its own (labels and up
    with the signal; exact with ``frontend`` and ``data.image``). For models that are not
    rotation-equivariant, which need their inputs level. The rotation used is stored in
    ``data.rotation [3, 3]``.

    Args:
        frontend: the :class:`~usf_graph.frontend.SphericalFrontend` that lifted the
            samples, for the exact path.
    """

    def __init__(self, frontend=None):
        self.frontend = frontend

    def forward(self, data: Data) -> Data:
        """``data`` turned level, ``data.up`` then +z."""
        up = getattr(data, "up", None)
        if up is None:
            raise ValueError("Level needs data.up, gravity's up in the sample's frame (an IMU: "
                             "RosBagFrames(imu=...), or the rooms datasets' views)")
        R = torch.as_tensor(level_rotation(up.detach().double().cpu().reshape(-1).numpy()))
        data = rotate_sample(data, R, self.frontend)
        data.rotation = R.to(data.pos.dtype)
        return data

    def __repr__(self) -> str:
        return f"{type(self).__name__}({'re-lift' if self.frontend is not None else 'grid-to-grid'})"


#: The label that :func:`rotate_sample` gives points it turns out of the field of view
#: (usf-graph's ignore index, ``scenes.classes.IGNORE``).
IGNORE_LABEL = 255


def rotate_sample(data: Data, R: torch.Tensor, frontend=None,
                  ignore_index: int = IGNORE_LABEL) -> Data:
    """``data`` with its signal turned by the rotation ``R`` (see :class:`RandomRotation`),
    and with it everything the view's frame fixes:

    * ``x`` and ``mask``: re-lifted (``frontend`` and ``data.image``) or resampled (a
      point is then seen where every grid point it is blended from is seen);
    * per-point labels ``y [N]`` (integers): the label of the nearest of the three grid
      points the turned point falls between, ``ignore_index`` where it leaves the field of
      view; a float ``y [N, ...]`` is resampled as ``x`` is;
    * gravity ``up [1, 3]`` (or ``[3]``): turned to ``R up``.

    The source pictures (``image``, ``label_image``) stay as they were taken. Spherical
    boxes are refused: turn them with :func:`usf_graph.ops.rotate_boxes`."""
    if getattr(data, "boxes", None) is not None:
        raise ValueError("rotate_sample turns the signal, labels and up of a sample, not its "
                         "spherical boxes: turn those with usf_graph.ops.rotate_boxes(boxes, R) "
                         "in your own transform, or render rotated views")
    R64 = torch.as_tensor(R, dtype=torch.float64)
    n = data.pos.shape[0]
    y = getattr(data, "y", None)
    per_point = isinstance(y, torch.Tensor) and y.dim() >= 1 and y.shape[0] == n
    image = getattr(data, "image", None)
    exact = frontend is not None and image is not None
    if not exact or per_point:
        pos = data.pos.detach().to(torch.float64).numpy()
        idx, w = barycentric_entries(pos, pos @ R64.numpy())  # row p: R^T p
        idx, w = torch.from_numpy(idx), torch.from_numpy(w)
    if exact:
        cam = frontend.camera
        fe = SphericalFrontend(cam.turned(R64.numpy()), frontend.grid,
                               frontend.interpolation, frontend.radius,
                               cache=GeometryCache(None, max_items=1))
        img = image.numpy() if isinstance(image, torch.Tensor) else image
        if img.ndim >= 3 and img.shape[0] == 1 and img.shape[1:3] == (cam.height, cam.width):
            img = img[0]  # stored per graph, as [1, H, W(, C)] (PyG batching)
        x = fe.lift(img)
        data.x, data.mask = x.to(data.x.dtype), fe.mask.clone()
    else:
        data.x = _resampled(data.x, idx, w)
        if getattr(data, "mask", None) is not None:
            # seen where every corner it reads (weight above rounding) is seen: a grid's
            # symmetry reads one corner, and the mask turns exactly
            data.mask = (data.mask[idx] | (w.abs() < 1e-9)).all(1)
            data.x = data.x * data.mask.reshape(-1, *([1] * (data.x.ndim - 1)))
    if per_point:
        if y.is_floating_point():
            data.y = _resampled(y, idx, w)
        else:
            data.y = y[idx[torch.arange(n), w.argmax(1)]]
            if getattr(data, "mask", None) is not None:  # [N] against labels [N, ...]
                seen = data.mask.reshape(-1, *([1] * (data.y.ndim - 1)))
                data.y = torch.where(seen, data.y, torch.full_like(data.y, ignore_index))
    up = getattr(data, "up", None)
    if isinstance(up, torch.Tensor) and up.shape[-1:] == (3,) and up.numel() == 3:
        data.up = (up.to(torch.float64) @ R64.T).to(up.dtype)
    return data


def _resampled(v: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Per-point values ``v [N, ...]`` at the turned points: barycentric blends."""
    flat = v if v.ndim >= 2 else v[:, None]
    out = (flat[idx] * w.to(v.dtype).reshape(*w.shape, *([1] * (flat.ndim - 1)))).sum(1)
    return out if v.ndim >= 2 else out[:, 0]


class GeodesicRadiusGraph(BaseTransform):
    r"""Connects points of S2 within geodesic distance ``r`` (radians).

    Sets ``edge_index [2, E]`` (row 0 neighbour, row 1 centre) and ``edge_attr [E, 1]``, the
    geodesic distance :math:`\operatorname{atan2}(|p \times q|, p \cdot q)` (PyG's
    ``Distance`` layout, as in :class:`SphericalImage`). Self-loops are included unless
    ``loop=False``; neighbourhoods are never truncated. Respects ``data.batch`` for
    batched samples.
    """

    def __init__(self, r: float, loop: bool = True):
        if not r > 0:
            raise ValueError(f"radius must be positive (radians), got {r}")
        self.r, self.loop = float(r), loop

    def forward(self, data: Data) -> Data:
        """Sets ``edge_index`` and ``edge_attr`` [E, 1] (geodesic distances) from ``data.pos``."""
        ei, ew = geodesic_radius_graph(data.pos.double(), self.r, getattr(data, "batch", None), self.loop)
        data.edge_index, data.edge_attr = ei, ew.to(data.pos.dtype)[:, None]
        return data

    def __repr__(self) -> str:
        return f"{type(self).__name__}(r={self.r:g}, loop={self.loop})"


class GaussianEdgeWeight(BaseTransform):
    r"""Writes ``edge_weight`` :math:`= \exp(-d^2 / 2\sigma^2)` from the distances in
    ``edge_attr [E, 1]``: an affinity in (0, 1], 1 on self-loops, the meaning PyG layers
    such as ``GCNConv``, ``GraphConv`` or ``SAGEConv``-with-weights give ``edge_weight``.

    Args:
        sigma: the length scale, in radians on S2 (default: half the largest edge).
    """

    def __init__(self, sigma: float | None = None):
        if sigma is not None and not sigma > 0:
            raise ValueError(f"sigma must be positive (radians), got {sigma}")
        self.sigma = sigma

    def forward(self, data: Data) -> Data:
        """Sets ``edge_weight`` [E] = exp(-d^2 / (2 sigma^2)) from the distances in ``edge_attr``.
        """
        d = getattr(data, "edge_attr", None)
        if d is None or d.dim() != 2 or d.shape[1] != 1:
            raise ValueError("GaussianEdgeWeight reads the distances from edge_attr [E, 1] (a "
                             "SphericalImage, or GeodesicRadiusGraph first)")
        d = d[:, 0]
        sigma = self.sigma if self.sigma is not None else 0.5 * float(d.max().clamp_min(1e-12))
        data.edge_weight = torch.exp(-0.5 * (d / sigma) ** 2)
        return data

    def __repr__(self) -> str:
        return f"{type(self).__name__}(sigma={self.sigma})"


class VisibleSubgraph(BaseTransform):
    r"""Keeps only the points the camera sees (``data.mask``) and the edges between them.

    Layers that take no mask (every PyG layer) would otherwise mix the zeros of unseen
    points into their neighbours. Node attributes (``x``, ``pos``, ``area``, ...) and edge
    attributes are subset alike (``Data.subgraph``); ``data.mask`` becomes all True.
    """

    def forward(self, data: Data) -> Data:
        """The subgraph of the points ``data.mask`` marks visible."""
        mask = getattr(data, "mask", None)
        if mask is None:
            raise ValueError("VisibleSubgraph needs data.mask (the points the camera sees)")
        if not bool(mask.any()):
            raise ValueError("data.mask is all False: the sample has no visible point")
        return data.subgraph(mask.bool())
