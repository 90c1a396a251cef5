"""PyG ``pre_transform`` for datasets stored as one ``[S, ...]`` tensor per field."""

from __future__ import annotations

from collections.abc import Callable, Iterable

import torch
from torch_geometric.data import Data


def pre_transform_stacked(pre_transform: Callable[[Data], Data], samples: Iterable[Data],
                          field: str, fixed: tuple[str, ...] = ()) -> torch.Tensor:
    """Apply ``pre_transform`` to every sample and stack ``field`` back into ``[S, ...]``.

    A split is stored as one tensor, so the transform must keep ``field`` one shape for
    every sample, and may not change the ``fixed`` attributes (e.g. a grid's ``pos``
    shared by all samples): both would be lost in storage, so they raise instead.
    """
    out = []
    for i, d in enumerate(samples):
        before = {k: d[k].clone() for k in fixed}
        t = pre_transform(d)
        v = getattr(t, field, None) if t is not None else None
        if v is None:
            raise ValueError(f"pre_transform returned no '{field}' for sample {i}; it must "
                             f"return a Data with '{field}'")
        if out and v.shape != out[0].shape:
            raise ValueError(f"pre_transform changed the shape of '{field}' to {tuple(v.shape)} "
                             f"for sample {i} (sample 0: {tuple(out[0].shape)}); this dataset "
                             f"stores the split as one tensor, so every sample needs one shape")
        for k in fixed:
            if not torch.equal(t[k], before[k]):
                raise ValueError(f"pre_transform changed '{k}', which all samples share and "
                                 f"which is not stored per sample; use it as a transform instead")
        out.append(v)
    return torch.stack(out)
