"""The two input forms of grid-bound layers: static ``[B, N, C]`` and PyG ``[sum N_i, C]``.

A layer built for one grid of N points (pooling, unpooling, the jet) takes one signal
``[N, C]``, a static batch ``[B, N, C]``, or a PyG batch ``[B N, C]`` with its ``batch``
vector. :func:`to_static` turns all three into ``[B, N, C]`` and :func:`from_static` turns
the result back.
"""

from __future__ import annotations

import torch


def to_static(x: torch.Tensor, num_nodes: int, batch: torch.Tensor | None = None,
              layer: str = "the layer") -> tuple[torch.Tensor, str]:
    """``x`` as ``[B, N, C]`` and its form (``"single"``, ``"static"`` or ``"pyg"``).
    Raises an error naming both numbers when the point count does not fit the grid."""
    n = int(num_nodes)
    if batch is not None:
        if x.dim() != 2 or batch.shape != (x.shape[0],):
            raise ValueError(f"with batch, {layer} takes x [sum N_i, C] and batch [sum N_i]; "
                             f"got x {tuple(x.shape)} and batch {tuple(batch.shape)}")
        sizes = torch.bincount(batch) if batch.numel() else batch.new_zeros(0)
        if not torch.equal(batch, pooled_batch(len(sizes), n, batch.device)):
            raise ValueError(f"{layer} was built for a grid of {n} points, but the batch has "
                             f"graphs of {sorted(set(sizes.tolist()))} points (or is not "
                             "sorted by graph); every graph must be on that grid")
        return x.view(len(sizes), n, x.shape[-1]), "pyg"
    if x.dim() not in (2, 3) or x.shape[-2] != n:
        raise ValueError(f"x has {x.shape[-2] if x.dim() >= 2 else 'no'} points "
                         f"(shape {tuple(x.shape)}), {layer} was built for a grid of {n}; "
                         "pass [N, C], [B, N, C], or a PyG batch [B N, C] with batch=")
    return (x.unsqueeze(0), "single") if x.dim() == 2 else (x, "static")


def mask_static(mask: torch.Tensor | None, x: torch.Tensor, form: str) -> torch.Tensor | None:
    """A mask for the static ``x [B, N, C]``: ``[N]`` or ``[B, N]`` (``[B N]`` in PyG form)
    -> bool ``[B, N]``; ``None`` stays ``None``."""
    if mask is None:
        return None
    B, N = x.shape[:2]
    m = mask.bool()
    if form == "pyg" and m.shape == (B * N,):
        return m.view(B, N)
    if m.shape == (N,):
        return m.expand(B, N)
    if form == "static" and m.shape == (B, N):
        return m
    raise ValueError(f"mask must have one value per point: [{N}] or [B, {N}] for [B, N, C] "
                     f"input, [sum N_i] for a PyG batch; got {tuple(mask.shape)}")


def from_static(y: torch.Tensor, form: str, mask: torch.Tensor | None = None,
                given: torch.Tensor | None = None):
    """Undo :func:`to_static` for an output ``y [B, M, C']`` and its mask ``[B, M]``. In
    the static form the mask comes back as ``[M]`` unless the ``given`` input mask was
    per sample (``[B, N]``)."""
    B, M = y.shape[:2]
    if form == "single":
        return y[0], None if mask is None else mask[0]
    if form == "pyg":
        return y.reshape(B * M, -1), None if mask is None else mask.reshape(B * M)
    if mask is not None and (given is None or given.dim() == 1):
        mask = mask[0]
    return y, mask


def check_per_point(name: str, t: torch.Tensor | None, n: int, max_dim: int = 1) -> None:
    """Raise unless ``t`` (a mask, areas) has one value per point: last dimension ``n``, at
    most ``max_dim`` dimensions (2 allows per-sample ``[B, N]``)."""
    if t is not None and (t.dim() < 1 or t.shape[-1] != n or t.dim() > max_dim):
        raise ValueError(f"{name} must have one value per point ({n}), got {tuple(t.shape)}")


def pooled_batch(num_graphs: int, num_points: int, device) -> torch.Tensor:
    """PyG's ``batch`` vector for ``num_graphs`` graphs of ``num_points`` points each."""
    return torch.arange(num_graphs, device=device).repeat_interleave(num_points)
