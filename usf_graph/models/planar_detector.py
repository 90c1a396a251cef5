"""The planar baseline: CenterNet on the equirectangular image, boxes from pixel coordinates."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from ..cameras import Equirectangular
from ..geometry import to_latlon
from .centernet import (
    Detector,
    box_centres,
    focal_loss,
    heatmap_targets,
    neighbour_table,
)
from .detector import MAX_FOV
from .planar_seg import PlanarUNet


def _ring(H: int, W: int) -> torch.Tensor:
    """Edges ``[2, E]`` (neighbour, centre) from each pixel of an ``H x W`` panorama to
    itself and its 8 neighbours, wrapping in longitude."""
    r, c = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    centre = (r * W + c).ravel()
    edges = []
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            rr = r + dr
            ok = ((rr >= 0) & (rr < H)).ravel()
            nb = (np.clip(rr, 0, H - 1) * W + (c + dc) % W).ravel()
            edges.append(np.stack([nb[ok], centre[ok]]))
    return torch.as_tensor(np.concatenate(edges, 1))


class PlanarDetector(Detector):
    r"""CenterNet on equirectangular images, the baseline of :class:`SphericalDetector`.

    A plain Conv2d U-Net (max-pooling down, bilinear upsampling with skip connections)
    from ``[B, in_channels, H, W]`` to a map at half resolution, where each pixel predicts
    ``num_classes`` heatmap logits and the box at it as a panorama detector does: the
    sub-pixel centre offset ``(du, dv)``, ``log fov_x``, ``log fov_y`` and the roll, all
    read in the image's own terms. Boxes are decoded from pixel coordinates, so they are
    tied to the panorama's latitude/longitude layout: the comparison the spherical head
    is built to win under rotation. ``gray``: it reads the input's luma only (mono cameras;
    :func:`~usf_graph.nn.colour.grayscale`).

    Shapes: ``x [B, C, H, W]`` -> ``{"heat": [B, M, num_classes], "box": [B, M, 5],
    "mask": [M] or None, "seen": [H W] or None}`` with M = (H/2)(W/2) output pixels in
    raster order (``mask``: those the camera sees in part; ``seen``: the input's mask).
    """

    def __init__(self, num_classes: int = 12, in_channels: int = 3, height: int = 128,
                 width: int = 256, channels=(16, 32, 64, 128), gray: bool = False):
        super().__init__()
        self.input_dims = 4
        depth = len(channels)
        if height % 2 ** (depth - 1) or width % 2 ** (depth - 1):
            raise ValueError(f"height and width must be divisible by {2 ** (depth - 1)}, got "
                             f"{height}x{width}")
        self.config = dict(num_classes=num_classes, in_channels=in_channels, height=height,
                           width=width, channels=list(channels), gray=gray)
        self.num_classes = num_classes
        self.body = PlanarUNet(num_classes + 5, in_channels, channels, out_stride=2, gray=gray)
        self.out_camera = Equirectangular(width // 2, height // 2)
        rays, _ = self.out_camera.lens_normal_map()
        self.register_buffer("points", torch.as_tensor(rays.reshape(-1, 3)), persistent=False)
        rays, _ = Equirectangular(width, height).lens_normal_map()
        self.register_buffer("input_pos", torch.as_tensor(rays.reshape(-1, 3)), persistent=False)
        self.spacing = math.pi / (height // 2)
        self.register_buffer("ring", neighbour_table(_ring(height // 2, width // 2),
                                                     (height // 2) * (width // 2)), persistent=False)
        self.reset_parameters()

    @property
    def gray(self) -> bool:
        """Whether it reads only its input's luma: its body's setting, not a copy."""
        return self.body.gray

    @gray.setter
    def gray(self, value: bool) -> None:
        self.body.gray = bool(value)

    def reset_parameters(self) -> None:
        """Re-initializes every layer; the heatmap biases start at -4.6 (CenterNet's 0.01 prior)."""
        self.body.reset_parameters()
        with torch.no_grad():
            self.body.head[-1].bias[: self.num_classes].fill_(-4.6)

    @classmethod
    def from_config(cls, config: dict) -> PlanarDetector:
        return cls(**config)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> dict:
        """Heatmaps and boxes per output pixel (class docstring) for ``x [B, C, H, W]``, optional
        ``mask [H, W]``.
        """
        H, W = self.config["height"], self.config["width"]
        if x.dim() != 4 or tuple(x.shape[1:]) != (self.config["in_channels"], H, W):
            raise ValueError(f"expected x [B, {self.config['in_channels']}, {H}, {W}], got "
                             f"{tuple(x.shape)}")
        f = self.body(x).flatten(2).transpose(1, 2)  # [B, M, C + 5]
        seen = None
        if mask is not None:
            seen = mask.reshape(-1).bool()
            mask = nn.functional.max_pool2d(mask.view(1, 1, H, W).float(), 2).flatten().bool()
        return {"heat": f[..., : self.num_classes], "box": f[..., self.num_classes:], "mask": mask,
                "seen": seen}

    def _pixels(self, points: torch.Tensor) -> torch.Tensor:
        uv, _ = self.out_camera.project(points.detach().double().cpu().numpy())
        return torch.as_tensor(uv, device=points.device)

    def loss(self, out: dict, boxes: torch.Tensor, classes: torch.Tensor,
             image: torch.Tensor) -> tuple[torch.Tensor, dict]:
        """Focal loss plus weighted L1 on offset (pixels), log sizes and roll at the
        regression samples of :func:`heatmap_targets`, as for the spherical detector."""
        B, W = out["heat"].shape[0], self.out_camera.width
        heat_t, _, (pt, box, w) = heatmap_targets(self.points, boxes.double(), classes, image, B,
                                                  self.num_classes, self.spacing)
        mask = None if out["mask"] is None else out["mask"].expand(B, -1)
        heat = focal_loss(out["heat"], heat_t.to(out["heat"].dtype), mask)
        if len(boxes) == 0:
            return heat + out["box"].sum() * 0, {"heat": heat.item(), "box": 0.0}
        uv = self._pixels(box_centres(boxes.double()))[box]
        off = torch.stack([uv[:, 0] - pt % W, uv[:, 1] - pt // W], -1)
        off[:, 0] = torch.remainder(off[:, 0] + W / 2, W) - W / 2  # across the seam
        t = torch.cat([off, boxes[box, 2:4].double().log(), boxes[box, 4:5].double()], -1)
        err = (out["box"][image[box], pt] - t.to(out["box"].dtype)).abs().sum(-1)
        reg = (err * (w / w.sum()).to(err.dtype)).sum()
        return heat + reg, {"heat": heat.item(), "box": reg.item()}

    def boxes_at(self, out: dict, b: int, point: torch.Tensor) -> torch.Tensor:
        """The boxes ``[k, 5]`` that image ``b``'s map gives at output pixels ``point``:
        centres from pixel coordinates (the panorama's layout), sizes and roll as read."""
        W = self.out_camera.width
        bx = out["box"][b, point]
        uv = torch.stack([point % W + bx[:, 0], point // W + bx[:, 1]], -1)
        rays, _ = self.out_camera.unproject(uv.detach().cpu().double().numpy())
        lat, lon = to_latlon(np.nan_to_num(rays, nan=1.0))
        fov = bx[:, 2:4].exp().clamp(max=MAX_FOV)
        roll = torch.remainder(bx[:, 4] + np.pi / 2, np.pi) - np.pi / 2
        centre = torch.as_tensor(np.stack([lon, lat], -1).reshape(-1, 2), dtype=bx.dtype,
                                 device=bx.device)
        return torch.cat([centre, fov, roll[:, None]], -1)
