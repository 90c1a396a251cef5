"""Planar baselines for dense prediction on equirectangular images: a U-Net and a
DeepLab v3-style network (Conv2d, zero padding, as panorama codebases use them)."""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from ..nn.colour import check_gray, grayscale


def conv_block(c_in: int, c_out: int, dilation: int = 1) -> nn.Sequential:
    """3x3 conv (no bias) -> BatchNorm -> ReLU."""
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, padding=dilation, dilation=dilation, bias=False),
                         nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


def _encoder(c_in: int, channels) -> nn.ModuleList:
    """Two conv blocks per level (the first level at full resolution)."""
    down = nn.ModuleList()
    for c in channels:
        down.append(nn.Sequential(conv_block(c_in, c), conv_block(c, c)))
        c_in = c
    return down


def _encode(down: nn.ModuleList, x: torch.Tensor) -> list:
    """Each level's features, max-pooling 2x between levels."""
    feats = []
    for i, block in enumerate(down):
        x = block(x if i == 0 else F.max_pool2d(x, 2))
        feats.append(x)
    return feats


def _checked_image(x: torch.Tensor, c: int, multiple: int, gray: bool) -> torch.Tensor:
    """``x``, checked, as the network reads it (its luma with ``gray``)."""
    if x.dim() != 4 or x.shape[1] != c or x.shape[2] % multiple or x.shape[3] % multiple:
        raise ValueError(f"expected x [B, {c}, H, W] with H and W divisible by {multiple}, got "
                         f"{tuple(x.shape)}")
    return grayscale(x, 1) if gray else x


class PlanarUNet(nn.Module):
    r"""A Conv2d U-Net: two conv blocks per level, max-pooling down, bilinear upsampling
    with skip connections up to ``1 / out_stride`` of the input, then a conv block and a
    1x1 conv to ``num_classes`` outputs per pixel.

    Fully convolutional: any ``H, W`` divisible by ``2 ** (len(channels) - 1)``. ``gray``:
    it reads the input's luma only (:func:`~usf_graph.nn.colour.grayscale`; for mono
    cameras).

    Shapes: ``x [B, in_channels, H, W]`` -> ``[B, num_classes, H / out_stride,
    W / out_stride]``.
    """

    def __init__(self, num_classes: int = 13, in_channels: int = 3, channels=(32, 64, 128, 128),
                 out_stride: int = 1, gray: bool = False):
        super().__init__()
        k = {1: 0, 2: 1, 4: 2}.get(out_stride)
        if k is None or k >= len(channels):
            raise ValueError(f"out_stride must be 1, 2 or 4 (and coarser than the deepest level), "
                             f"got {out_stride}")
        self.config = dict(num_classes=num_classes, in_channels=in_channels,
                           channels=list(channels), out_stride=out_stride, gray=gray)
        self.input_dims, self.in_channels = 4, in_channels
        self.gray = check_gray(gray, in_channels)
        self.multiple = 2 ** (len(channels) - 1)
        self.down, c_in = _encoder(in_channels, channels), channels[-1]
        self.up = nn.ModuleList()
        for c in reversed(channels[k:-1]):
            self.up.append(conv_block(c_in + c, c))
            c_in = c
        self.head = nn.Sequential(conv_block(c_in, c_in), nn.Conv2d(c_in, num_classes, 1))

    @classmethod
    def from_config(cls, config: dict) -> PlanarUNet:
        return cls(**config)

    def reset_parameters(self) -> None:
        """Re-initializes every convolution and normalization."""
        for m in self.modules():
            if isinstance(m, (nn.Conv2d, nn.BatchNorm2d)):
                m.reset_parameters()

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """Logits ``[B, num_classes, H / out_stride, W / out_stride]`` for ``x [B, C, H, W]``
        (``mask`` is accepted for a uniform call and not read: the image is its own support).
        """
        skips = _encode(self.down, _checked_image(x, self.in_channels, self.multiple, self.gray))
        x = skips.pop()
        for block in self.up:
            skip = skips.pop()
            x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            x = block(torch.cat([x, skip], 1))
        return self.head(x)


class _ASPP(nn.Module):
    """Atrous spatial pyramid pooling: a 1x1 conv, dilated 3x3 convs and image pooling in
    parallel, concatenated and fused by a 1x1 conv."""

    def __init__(self, c_in: int, c_out: int, rates):
        super().__init__()
        self.branches = nn.ModuleList(
            [nn.Sequential(nn.Conv2d(c_in, c_out, 1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU())]
            + [conv_block(c_in, c_out, r) for r in rates])
        self.pool = nn.Sequential(nn.Conv2d(c_in, c_out, 1), nn.ReLU())
        self.fuse = nn.Sequential(nn.Conv2d(c_out * (len(rates) + 2), c_out, 1, bias=False),
                                  nn.BatchNorm2d(c_out), nn.ReLU())

    def forward(self, x):
        g = self.pool(x.mean((-2, -1), keepdim=True)).expand(-1, -1, *x.shape[-2:])
        return self.fuse(torch.cat([b(x) for b in self.branches] + [g], 1))


class PlanarDeepLab(nn.Module):
    r"""DeepLab v3 on the equirectangular image: a conv backbone down to stride
    ``2 ** (len(channels) - 1)``, ASPP (``rates``, image pooling), then the v3+ decoder
    (upsample, concatenate the stride-1 features, one conv block) and a 1x1 conv.
    ``gray``: as :class:`PlanarUNet`'s.

    Shapes: ``x [B, in_channels, H, W]`` -> ``[B, num_classes, H, W]``.
    """

    def __init__(self, num_classes: int = 13, in_channels: int = 3, channels=(32, 64, 128, 128),
                 aspp_channels: int = 128, rates=(2, 4, 6), gray: bool = False):
        super().__init__()
        self.config = dict(num_classes=num_classes, in_channels=in_channels,
                           channels=list(channels), aspp_channels=aspp_channels, rates=list(rates),
                           gray=gray)
        self.input_dims, self.in_channels = 4, in_channels
        self.gray = check_gray(gray, in_channels)
        self.multiple = 2 ** (len(channels) - 1)
        self.down, c_in = _encoder(in_channels, channels), channels[-1]
        self.aspp = _ASPP(c_in, aspp_channels, rates)
        low = channels[0]
        self.decoder = conv_block(aspp_channels + low, low)
        self.head = nn.Conv2d(low, num_classes, 1)

    @classmethod
    def from_config(cls, config: dict) -> PlanarDeepLab:
        return cls(**config)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """Logits ``[B, num_classes, H, W]`` for ``x [B, C, H, W]`` (``mask`` accepted, not read).
        """
        feats = _encode(self.down, _checked_image(x, self.in_channels, self.multiple, self.gray))
        low, x = feats[0], feats[-1]
        x = F.interpolate(self.aspp(x), size=low.shape[-2:], mode="bilinear", align_corners=False)
        return self.head(self.decoder(torch.cat([x, low], 1)))


__all__ = ["PlanarUNet", "PlanarDeepLab", "conv_block"]
