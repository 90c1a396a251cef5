"""RigFrontend: the cameras of a rig lifted onto one spherical image."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch

from ..cameras import Camera, stitch_at
from ..cameras.base import angle_to
from ..grids import Grid
from .cache import GeometryCache
from .frontend import SphericalFrontend
from .image import SphericalImage

BLENDS = ("best", "feather")


class RigFrontend:
    r"""Lifts the images of several cameras onto one grid, as one :class:`SphericalImage`.

    The cameras are mounted by their ``rotation`` (camera -> rig, e.g. from
    :func:`usf_graph.cameras.load_rig`). Without a ``distance`` they share one centre of
    projection: the baseline between them is ignored, which holds for scenes far away
    compared to it. With one, each camera looks from its ``position`` at a scene sphere of
    that radius about ``centre`` (:func:`usf_graph.cameras.stitch_at`), so that points at
    that distance line up across the seams.

    Args:
        cameras: the cameras, a sequence or a ``{name: camera}`` mapping.
        grid: the :class:`~usf_graph.grids.Grid` they are lifted onto.
        interpolation, radius, cache: as in :class:`SphericalFrontend`.
        blend: where several cameras see a point, ``best`` takes the one whose optical
            axis is nearest to it (seams are sharp, every value comes from one camera);
            ``feather`` averages them with weights
            :math:`w_c \propto \theta^{\max}_c - \theta_c`, the angle left to the edge of
            camera :math:`c`'s field (seams are smooth).
        distance: the stitching distance, in the unit of the cameras' positions (metres
            for the calibration files); ``None``: at infinity.
        centre: the scene sphere's centre, ``"mean"`` (of the cameras' positions) or 3
            numbers in the rig's sphere frame; used with a ``distance``.

    Attributes:
        mask: ``[N]`` bool, points some camera sees (the joint field of view).
        weights: ``[K, N]`` float64 blend weights, summing to 1 on seen points.
        source: ``[N]`` long, the camera that sees each point best (-1: none).
    """

    def __init__(self, cameras: Sequence[Camera] | Mapping[str, Camera], grid: Grid,
                 interpolation: str = "bilinear", blend: str = "best",
                 radius: float | None = None, cache: GeometryCache | None = None,
                 distance: float | None = None, centre="mean"):
        if blend not in BLENDS:
            raise ValueError(f"blend must be one of {BLENDS}, got {blend!r}")
        if isinstance(cameras, Mapping):
            self.names, cams = list(cameras), list(cameras.values())
        else:
            cams = list(cameras)
            self.names = [f"cam{i}" for i in range(len(cams))]
        if not cams:
            raise ValueError("a rig needs at least one camera")
        if distance is not None:
            cams = list(stitch_at(dict(zip(self.names, cams)), distance, centre).values())
        self.grid, self.blend = grid, blend
        self.frontends = [SphericalFrontend(c, grid, interpolation, radius, cache=cache)
                          for c in cams]
        seen = torch.stack([fe.mask for fe in self.frontends]).numpy()  # [K, N]
        pos = grid.pos.numpy()
        ang = np.stack([angle_to(c.to_optical(pos), c.optical_axis) for c in cams])
        ang = np.where(seen, ang, np.inf)
        best = ang.argmin(0)
        self.mask = torch.from_numpy(seen.any(0))
        self.source = torch.from_numpy(np.where(seen.any(0), best, -1))
        if blend == "best":
            w = (np.arange(len(cams))[:, None] == best[None]) & seen
            w = w.astype(np.float64)
        else:
            edge = np.array([c.max_incidence for c in cams])[:, None]
            w = np.where(seen, np.maximum(edge - ang, 0.0), 0.0)
            tot = w.sum(0)
            # a point only seen at the very edge of every camera takes the best one
            w = np.where(tot > 0, w / np.where(tot > 0, tot, 1), (w == 0) & (ang == ang.min(0)))
            w = np.where(seen, w, 0.0)
        self.weights = torch.from_numpy(w)

    @classmethod
    def from_file(cls, path, grid: Grid, **kw) -> RigFrontend:
        """A rig from a Kalibr camchain, a Basalt calibration, ORB-SLAM3 settings or a
        COLMAP model (:func:`usf_graph.cameras.load_rig`)."""
        from ..cameras import load_rig

        return cls(load_rig(path), grid, **kw)

    @property
    def cameras(self) -> list[Camera]:
        return [fe.camera for fe in self.frontends]

    @property
    def edge_index(self) -> torch.Tensor:
        return self.frontends[0].edge_index

    @property
    def edge_weight(self) -> torch.Tensor:
        return self.frontends[0].edge_weight

    def __repr__(self) -> str:
        cams = ", ".join(f"{n}={c.model}" for n, c in zip(self.names, self.cameras))
        dist = self.cameras[0].distance
        at = "" if dist is None else f", distance={dist:g}"
        return (f"RigFrontend({cams}; {self.grid!r}, blend='{self.blend}'{at}, "
                f"visible={int(self.mask.sum())}/{len(self.grid)})")

    def _ordered(self, images) -> list:
        if isinstance(images, Mapping):
            missing = [n for n in self.names if n not in images]
            if missing:
                raise ValueError(f"no image for camera(s) {missing}; the rig has {self.names}")
            images = [images[n] for n in self.names]
        images = list(images)
        if len(images) != len(self.frontends):
            raise ValueError(f"the rig has {len(self.frontends)} cameras ({self.names}) but "
                             f"{len(images)} images were given, one per camera in that order")
        return images

    def _blend(self, parts: list[torch.Tensor]) -> torch.Tensor:
        out = None
        for w, x in zip(self.weights, parts):
            term = x * w.to(x.dtype)[:, None]
            out = term if out is None else out + term
        return out

    def lift(self, images) -> torch.Tensor:
        """One image per camera (a sequence in camera order, or ``{name: image}``) ->
        ``[N, C]``; points no camera sees are 0."""
        return self._blend([fe.lift(im) for fe, im in zip(self.frontends, self._ordered(images))])

    def lift_batch(self, images) -> torch.Tensor:
        """One ``[B, H, W, C]`` batch per camera -> ``[B, N, C]``."""
        return self._blend([fe.lift_batch(im) for fe, im in
                            zip(self.frontends, self._ordered(images))])

    def __call__(self, images) -> SphericalImage:
        x = self.lift(images)
        return self.frontends[0].image(x, self.mask)
