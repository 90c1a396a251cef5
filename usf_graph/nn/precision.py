"""Half precision around geometry: what runs in float32, and what ``.half()`` leaves alone.

Distances, areas, points and sparse operators are geometry. Rounded to bfloat16 they lose
all but three digits, and one :class:`~usf_graph.nn.SphericalConv` then misses its
float64 reference by about 9% (0.2% when only its input is bfloat16). So the sums over a
neighbourhood run in float32 (:func:`accumulate_in`), and :class:`GeometryModule`'s
geometry keeps its dtype when the module is cast to half precision."""

from __future__ import annotations

import torch
from torch import nn

HALF = (torch.float16, torch.bfloat16)


def accumulate_in(dtype: torch.dtype) -> torch.dtype:
    """The dtype a sparse product over ``dtype`` values runs in: float32 for float16 and
    bfloat16 (torch's CPU sparse CSR products have no kernels for them, and sums over a
    neighbourhood lose digits there), else ``dtype`` itself."""
    return torch.float32 if dtype in HALF else dtype


class GeometryModule(nn.Module):
    """Base of the modules whose non-persistent floating buffers are geometry. ``.half()``,
    ``.bfloat16()`` or ``.to(torch.float16)`` cast the parameters and move such buffers to
    the new device but keep their dtype; every other cast (``.double()``, ``.float()``,
    ``.to(device)``) applies to them as to any buffer. Half-precision inputs meet them
    through :func:`accumulate_in`."""

    def _apply(self, fn, recurse=True):
        geometry = {name: b for name, b in self._buffers.items()
                    if b is not None and b.is_floating_point() and b.dtype not in HALF
                    and name in self._non_persistent_buffers_set}
        super()._apply(fn, recurse)
        for name, before in geometry.items():
            after = self._buffers.get(name)
            if after is not None and after.dtype in HALF:
                self._buffers[name] = before.to(after.device)
        return self
