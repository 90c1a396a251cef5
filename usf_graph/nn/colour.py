"""Gray inputs for models of mono cameras: colour channels replaced by their luma."""

from __future__ import annotations

import torch

#: ITU-R BT.601 luma weights of R, G, B: what ``cv2.cvtColor(..., COLOR_RGB2GRAY)`` uses.
LUMA = (0.299, 0.587, 0.114)


def grayscale(x: torch.Tensor, dim: int = -1) -> torch.Tensor:
    r"""``x`` with its three colour channels along ``dim`` each replaced by the luma
    :math:`Y = 0.299 R + 0.587 G + 0.114 B` (:data:`LUMA`), so that a model built for RGB
    reads a mono camera's image, R = G = B = Y, and a colour image as that camera would
    record it. A gray image (R = G = B) stays as it is: the weights sum to 1.

    Shapes: ``x [..., 3, ...]`` (3 along ``dim``) -> the same shape."""
    if x.shape[dim] != 3:
        raise ValueError(f"a gray model reads RGB images (3 channels along dim {dim}), got shape "
                         f"{tuple(x.shape)}")
    w = torch.tensor(LUMA, dtype=x.dtype, device=x.device)
    shape = [1] * x.dim()
    shape[dim] = 3
    y = (x * w.view(shape)).sum(dim, keepdim=True)
    return y.expand_as(x).contiguous()


def check_gray(gray: bool, in_channels: int) -> bool:
    """``gray`` as a bool, after checking that a gray model reads RGB (``in_channels`` 3)."""
    if gray and in_channels != 3:
        raise ValueError(f"gray=True reads the luma of RGB inputs: it needs in_channels=3, got "
                         f"{in_channels}")
    return bool(gray)


def read_gray(model) -> int:
    """Makes ``model`` read only its inputs' luma from now on, as a model built with
    ``gray=True`` does: every submodule with a ``gray`` flag (the models, their up
    estimates) gets it set. For scoring a colour model on a mono camera's images; its
    config (what a checkpoint saves) does not change. Returns how many it set (0: nothing
    in ``model`` reads colour that way)."""
    mods = [m for m in model.modules() if isinstance(getattr(m, "gray", None), bool)]
    for m in mods:
        m.gray = True
    return len(mods)


__all__ = ["LUMA", "grayscale", "check_gray", "read_gray"]
