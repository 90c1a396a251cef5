"""Point-cloud models: PointConv blocks with FPS pooling (SE(3) invariant) and a PointNet
baseline that reads raw coordinates."""

from __future__ import annotations

import torch
from torch import nn

from ..nn import FPSPool, PointConv, euclidean_radius_graph


def _flatten(pos: torch.Tensor, batch):
    """``[B, N, 3]`` -> (``[B*N, 3]``, batch, B) or ``[N, 3]`` + batch -> as is."""
    if pos.dim() == 3:
        B, N, _ = pos.shape
        return pos.reshape(B * N, 3), torch.arange(B, device=pos.device).repeat_interleave(N), B
    if batch is None:
        batch = torch.zeros(len(pos), dtype=torch.long, device=pos.device)
    return pos, batch, int(batch.max()) + 1 if len(batch) else 0


def _mlp(*sizes: int) -> nn.Sequential:
    layers = []
    for a, b in zip(sizes[:-2], sizes[1:-1]):
        layers += [nn.Linear(a, b), nn.BatchNorm1d(b), nn.ReLU()]
    return nn.Sequential(*layers, nn.Linear(sizes[-2], sizes[-1]))


class PointCloudNet(nn.Module):
    r"""PointConv blocks at growing radii with FPS pooling: invariant to rigid motions.

    Every operation reads the cloud only through euclidean distances: the radius graphs,
    the :class:`~usf_graph.nn.PointConv` kernels, :class:`~usf_graph.nn.FPSPool`, the input
    features (1 and the distance to the centroid) and, with ``normalize_scale``, the
    division by the cloud's RMS radius. So for any rotation :math:`R` and translation
    :math:`t`, ``net(pos @ R.T + t) == net(pos)`` up to rounding.

    Args:
        num_classes: outputs per cloud (or per point with ``segmentation=True``).
        channels: features per stage; one FPS pooling between consecutive stages.
        radii: PointConv radius per stage, in units of the cloud's RMS radius.
        ratio: fraction of points kept by each FPS pooling.
        segmentation: per-point logits; coarse features return to the points by
            inverse-distance interpolation from the 3 nearest centres, plus skips.

    Shapes: ``pos [B, N, 3]`` or ``pos [N, 3]`` with ``batch [N]`` ->
    ``[B, num_classes]`` (or ``[B, N, num_classes]`` / ``[N, num_classes]``).
    """

    def __init__(self, num_classes: int, channels=(32, 64, 128), radii=(0.3, 0.6, 1.2),
                 ratio: float = 0.25, num_basis: int = 6, segmentation: bool = False,
                 normalize_scale: bool = True):
        super().__init__()
        if len(radii) != len(channels):
            raise ValueError(f"need one radius per stage: {len(channels)} channels, "
                             f"{len(radii)} radii")
        self.config = dict(num_classes=num_classes, channels=list(channels), radii=list(radii),
                           ratio=ratio, num_basis=num_basis, segmentation=segmentation,
                           normalize_scale=normalize_scale)
        self.radii, self.segmentation, self.normalize_scale = list(radii), segmentation, normalize_scale
        self.convs, self.norms, self.pools = nn.ModuleList(), nn.ModuleList(), nn.ModuleList()
        c_in = 2
        for s, (c, r) in enumerate(zip(channels, radii)):
            self.convs.append(PointConv(c_in, c, r, num_basis=num_basis, basis="gaussian"))
            self.norms.append(nn.BatchNorm1d(c))
            if s < len(channels) - 1:
                self.pools.append(FPSPool(ratio, r))
            c_in = c
        if segmentation:
            self.up = nn.ModuleList(_mlp(a + b, b, b) for a, b in
                                    zip(channels[:0:-1], channels[-2::-1]))
            self.head = _mlp(channels[0] + 2 * channels[-1], 64, num_classes)
        else:
            self.head = _mlp(2 * channels[-1], 128, num_classes)

    def forward(self, pos: torch.Tensor, batch: torch.Tensor | None = None) -> torch.Tensor:
        """Logits for clouds ``pos [B, N, 3]``, or ``pos [N, 3]`` with ``batch [N]``: ``[B,
        num_classes]``, per point with ``segmentation=True``.
        """
        from torch_scatter import scatter_max, scatter_mean  # compiled: imported where used

        shape = pos.shape
        pos, batch, B = _flatten(pos, batch)
        cen = scatter_mean(pos, batch, dim=0, dim_size=B)
        rel = pos - cen[batch]
        if self.normalize_scale:
            rms = scatter_mean(rel.pow(2).sum(-1), batch, dim_size=B).sqrt().clamp_min(1e-12)
            pos, rel = pos / rms[batch, None], rel / rms[batch, None]
        x = torch.stack([torch.ones_like(rel[:, 0]), rel.norm(dim=-1)], -1)
        levels = []
        for s, conv in enumerate(self.convs):
            ei, ew = euclidean_radius_graph(pos, self.radii[s], batch)
            x = torch.relu(self.norms[s](conv(x, ei, ew)))
            levels.append((x, pos, batch))
            if s < len(self.pools):
                x, pos, batch, _ = self.pools[s](x, pos, batch)
        glob = torch.cat([scatter_mean(x, batch, dim=0, dim_size=B),
                          scatter_max(x, batch, dim=0, dim_size=B)[0]], -1)
        if not self.segmentation:
            return self.head(glob)
        for (skip, p_f, b_f), up in zip(levels[-2::-1], self.up):
            x = up(torch.cat([_interpolate(x, pos, batch, p_f, b_f), skip], -1))
            pos, batch = p_f, b_f
        out = self.head(torch.cat([x, glob[batch]], -1))
        return out.view(*shape[:-1], -1)


def _interpolate(x, pos, batch, pos_f, batch_f, k: int = 3):
    """Features at ``pos_f`` from the ``k`` nearest of ``pos``, weighted by 1 / d^2."""
    import torch_cluster

    ei = torch_cluster.knn(pos, pos_f, k, batch, batch_f)  # row 0: fine index, row 1: coarse
    d2 = (pos_f[ei[0]] - pos[ei[1]]).pow(2).sum(-1)
    w = 1.0 / d2.clamp_min(1e-16)
    num = torch.zeros(len(pos_f), x.shape[1], dtype=x.dtype, device=x.device)
    num.index_add_(0, ei[0], x[ei[1]] * w[:, None])
    den = torch.zeros(len(pos_f), dtype=x.dtype, device=x.device).index_add_(0, ei[0], w)
    return num / den[:, None]


class PointNet(nn.Module):
    """PointNet-style baseline: a shared MLP on raw coordinates, max pooling, a head.

    It reads ``pos`` directly, so a rigid motion changes its input; it exists to show
    what is lost without invariance. Shapes as :class:`PointCloudNet` (classification).
    """

    def __init__(self, num_classes: int, channels=(64, 128, 256)):
        super().__init__()
        self.config = dict(num_classes=num_classes, channels=list(channels))
        self.point = _mlp(3, *channels)
        self.head = _mlp(channels[-1], 128, num_classes)

    def forward(self, pos: torch.Tensor, batch: torch.Tensor | None = None) -> torch.Tensor:
        """Logits ``[B, num_classes]`` for ``pos [B, N, 3]``, or ``pos [N, 3]`` with ``batch [N]``.
        """
        from torch_scatter import scatter_max

        pos, batch, B = _flatten(pos, batch)
        h = torch.relu(self.point(pos))
        return self.head(scatter_max(h, batch, dim=0, dim_size=B)[0])


