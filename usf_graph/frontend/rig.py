"""RigFrontend: the cameras of a rig lifted onto one spherical image."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import torch
from tqdm.auto import tqdm

from ..cameras import Camera, stitch_at
from ..cameras.base import angle_to
from ..cameras.rig import rig_centre
from ..grids import Grid
from .cache import GeometryCache
from .choices import BLENDS
from .frontend import SphericalFrontend, _as_image
from .image import SphericalImage
from .reimage import Reimager
from .remap import Remap, round_to


def blend_weights(cameras: Sequence[Camera], pos: np.ndarray, seen: np.ndarray,
                  blend: str = "best") -> tuple[np.ndarray, np.ndarray]:
    r"""How a rig's ``cameras`` share the directions ``pos [M, 3]`` that each sees
    (``seen [K, M]``): ``(weights [K, M]`` float64, summing to 1 where any camera sees,
    ``best [M]``: the camera whose optical axis is nearest, -1 where none sees). ``blend``:
    ``best`` gives each direction to that camera alone; ``feather`` weighs camera
    :math:`c` by :math:`\theta^{\max}_c - \theta_c`, the angle left to its field's edge."""
    if blend not in BLENDS:
        raise ValueError(f"blend must be one of {BLENDS}, got {blend!r}")
    ang = np.stack([angle_to(c.to_optical(pos), c.optical_axis) for c in cameras])
    ang = np.where(seen, ang, np.inf)
    best = ang.argmin(0)
    w = ((np.arange(len(cameras))[:, None] == best[None]) & seen).astype(np.float64)
    if blend == "feather":
        edge = np.array([c.max_incidence for c in cameras])[:, None]
        share = np.where(seen, np.maximum(edge - ang, 0.0), 0.0)
        tot = share.sum(0)
        # a point only seen at the very edge of every camera takes the best one
        w = np.where(tot > 0, share / np.where(tot > 0, tot, 1), w)
    return w, np.where(seen.any(0), best, -1)


def named_cameras(cameras: Sequence[Camera] | Mapping[str, Camera]) -> tuple[list[str], list[Camera]]:
    """A rig's camera names and cameras: a mapping's own, or ``cam0``, ``cam1``, ... for a
    sequence."""
    if isinstance(cameras, Mapping):
        return list(cameras), list(cameras.values())
    cams = list(cameras)
    return [f"cam{i}" for i in range(len(cams))], cams


def ordered_images(names: Sequence[str], images) -> list:
    """One image per camera of a rig whose cameras are ``names``, in that order: ``images``
    a sequence in that order, or ``{name: image}``."""
    names = list(names)
    if isinstance(images, Mapping):
        missing = [n for n in names if n not in images]
        if missing:
            raise ValueError(f"no image for camera(s) {missing}; the rig has {names}")
        images = [images[n] for n in names]
    images = list(images)
    if len(images) != len(names):
        raise ValueError(f"the rig has {len(names)} cameras ({', '.join(names)}) but "
                         f"{len(images)} images were given, one per camera in that order")
    return images


class RigReimager:
    """A rig's images (one per camera) re-imaged as ``cam_dst`` would see the scene from the
    rig's centre, with the geometry built once: each camera re-imaged alone
    (:class:`~usf_graph.frontend.reimage.Reimager`; stitched cameras look from their own
    centres) and blended as :class:`RigFrontend` blends them (:func:`blend_weights`). E.g.
    two back-to-back fisheyes stitched into an equirectangular panorama, frame after frame.

    Args:
        cameras: the rig, ``{name: Camera}`` (or a sequence, named ``cam0``, ``cam1``, ...).
        cam_dst: the camera to see the scene through.
        blend: ``best`` or ``feather`` (:func:`blend_weights`).
        interpolation: ``bilinear`` or ``nearest``.
        source_valid, target: each camera's readable pixels and ``cam_dst``'s
            ``lens_normal_map()``, where the caller has them (:class:`Reimager`).
    """

    def __init__(self, cameras: Sequence[Camera] | Mapping[str, Camera], cam_dst: Camera,
                 blend: str = "best", interpolation: str = "bilinear",
                 source_valid: Sequence[np.ndarray] | None = None,
                 target: tuple[np.ndarray, np.ndarray] | None = None):
        self._named = isinstance(cameras, Mapping)
        self.names, cams = named_cameras(cameras)
        self.cam_dst = cam_dst
        rays, valid = cam_dst.lens_normal_map() if target is None else target  # once for all
        ok = [None] * len(cams) if source_valid is None else list(source_valid)
        self._parts = [Reimager(c, cam_dst, interpolation, v, target=(rays, valid)) for c, v in zip(cams, ok)]
        pos = np.where(valid[..., None], rays, 1.0).reshape(-1, 3)
        w, best = blend_weights(cams, pos, np.stack([r.seen.ravel() for r in self._parts]), blend)
        # each camera samples only the pixels it has a share of: with "best", each pixel once
        self._fast = [r.part(wk > 0) for r, wk in zip(self._parts, w)]
        self._weights = w.astype(np.float32)[..., None]
        # every share all of a pixel: the cameras write their pixels into one image
        self._whole = blend == "best" and not any(c.wraps_u for c in cams)
        self.seen = (best >= 0).reshape(cam_dst.height, cam_dst.width)

    def __call__(self, images) -> np.ndarray:
        """One image per camera (in order, or ``{name: image}``) -> ``[H', W'(, C)]``:
        float32 for float images, an integer image's type (rounded) for integer ones. Pixels
        no camera sees are 0."""
        if not self._named and isinstance(images, Mapping):
            images = list(images.values())  # unnamed cameras: a mapping taken in its order
        images = ordered_images(self.names, images)
        arrs = [_as_image(im, r.cam_src)[0] for im, r in zip(images, self._parts)]
        if len({(a.shape[-1], a.dtype) for a in arrs}) > 1:
            raise ValueError("the rig's images differ in channels or type: "
                             f"{[(a.shape[-1], a.dtype.name) for a in arrs]}; give them alike")
        c, dtype = arrs[0].shape[-1], arrs[0].dtype
        n = self.cam_dst.height * self.cam_dst.width
        if self._whole and Remap.accepts(arrs[0]):  # in the images' own type
            out = self._fast[0].blank(c, dtype)
            for fast, a in zip(self._fast, arrs):
                fast(a, into=out)
            out = out[:n]
        else:
            out = np.zeros((n, c), np.float32)
            for fast, wk, r, a in zip(self._fast, self._weights, self._parts, arrs):
                a = a if a.dtype == np.float32 else a.astype(np.float32)
                out += wk * (fast(a) if Remap.accepts(a) else r(a).reshape(n, c))
            if np.issubdtype(dtype, np.integer):  # as a Reimager keeps an integer image's type
                out = round_to(out, dtype)
        out = out.reshape(self.cam_dst.height, self.cam_dst.width, c)
        return out[..., 0] if np.ndim(images[0]) == 2 else out


def render_rig(images, cameras: Sequence[Camera] | Mapping[str, Camera], cam_dst: Camera,
               blend: str = "best", interpolation: str = "bilinear") -> np.ndarray:
    """A rig's images (one per camera, in order, or ``{name: image}``) re-imaged as
    ``cam_dst`` would see the scene from the rig's centre: :class:`RigReimager` for one
    frame (build one for many). Pixels no camera sees are 0. Returns ``[H', W'(, C)]``
    float32 (integer images: their type)."""
    return RigReimager(cameras, cam_dst, blend, interpolation)(images)


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
        if blend not in BLENDS:  # before any table is built
            raise ValueError(f"blend must be one of {BLENDS}, got {blend!r}")
        self.names, cams = named_cameras(cameras)
        if not cams:
            raise ValueError("a rig needs at least one camera")
        if distance is not None:
            cams = list(stitch_at(dict(zip(self.names, cams)), distance, centre).values())
        self.grid, self.blend = grid, blend
        self.frontends = [SphericalFrontend(c, grid, interpolation, radius, cache=cache)
                          for c in cams]
        seen = torch.stack([fe.mask for fe in self.frontends]).numpy()  # [K, N]
        w, best = blend_weights(cams, grid.pos.numpy(), seen, blend)
        self.mask = torch.from_numpy(seen.any(0))
        self.source = torch.from_numpy(best)
        self.weights = torch.from_numpy(w)

    @classmethod
    def from_file(cls, path, grid: Grid, **kw) -> RigFrontend:
        """A rig from a Kalibr camchain, a Basalt calibration, ORB-SLAM3 settings or a
        COLMAP model (:func:`usf_graph.cameras.load_rig`)."""
        from ..cameras import load_rig

        return cls(load_rig(path), grid, **kw)

    @property
    def cameras(self) -> list[Camera]:
        """The rig's cameras, in the order of the images :meth:`lift` takes."""
        return [fe.camera for fe in self.frontends]

    @property
    def edge_index(self) -> torch.Tensor:
        """The grid's radius graph ``[2, E]`` (shared by every camera's frontend)."""
        return self.frontends[0].edge_index

    @property
    def edge_weight(self) -> torch.Tensor:
        """Its geodesic distances ``[E]`` in radians."""
        return self.frontends[0].edge_weight

    def __repr__(self) -> str:
        cams = ", ".join(f"{n}={c.model}" for n, c in zip(self.names, self.cameras))
        dist = self.cameras[0].distance
        at = "" if dist is None else f", distance={dist:g}"
        return (f"RigFrontend({cams}; {self.grid!r}, blend='{self.blend}'{at}, "
                f"visible={int(self.mask.sum())}/{len(self.grid)})")

    def _ordered(self, images) -> list:
        return ordered_images(self.names, images)

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


#: Distances :func:`choose_distance` tries by default (in the calibration's unit; None: infinity).
DISTANCES = tuple(float(d) for d in np.geomspace(0.5, 32.0, 13)) + (None,)


def choose_distance(cameras: Mapping[str, Camera], grid: Grid, images,
                    candidates=DISTANCES, centre="mean", interpolation: str = "bilinear",
                    progress: bool = False) -> tuple[float | None, dict]:
    r"""The stitching distance at which the rig's cameras agree best where they overlap.

    For each candidate :math:`r` every camera is lifted alone (stitched at :math:`r`), and
    the seam error is the area-weighted mean over the points several cameras see of
    :math:`|x_i - x_j|` over the pairs of cameras that see them (and the channels). A
    scene at one depth gives its least error at that depth; a room, a compromise.

    Args:
        cameras: the rig (``{name: camera}`` with positions, :func:`cameras.load_rig`).
        grid: the grid to compare on (a coarse one is enough, e.g. ``icosahedral:4``).
        images: one image per camera, in the rig's order.
        candidates: the distances to try; ``None`` is infinity. Those the rig's cameras
            reach past are left out.

    Returns:
        ``(best distance, {distance: seam error})``; the errors are in the images' unit,
        infinite where no two cameras overlap.
    """
    names, cams = list(cameras), list(cameras.values())
    if len(cams) < 2:
        raise ValueError("choosing a stitching distance compares cameras: the rig needs two")
    images = ordered_images(names, images)
    far = rig_centre(cameras, centre)[1]
    tries = [d for d in candidates if d is None or d > far * (1 + 1e-9)]
    if not tries:
        raise ValueError(f"every candidate distance lies within the rig (its cameras are up "
                         f"to {far:.4g} from its centre); try farther ones")
    area = grid.area.double()
    cache = GeometryCache(None, max_items=len(cams))
    errors = {}
    for d in tqdm(tries, desc="stitching distances", disable=not progress):
        fes = [SphericalFrontend(c, grid, interpolation, cache=cache)
               for c in stitch_at(dict(zip(names, cams)), d, centre).values()]
        xs = [fe.lift(im).double() for fe, im in zip(fes, images)]
        num = torch.zeros(len(grid), dtype=torch.float64)
        pairs = torch.zeros(len(grid), dtype=torch.float64)
        for i in range(len(xs)):
            for j in range(i + 1, len(xs)):
                both = (fes[i].mask & fes[j].mask).double()
                num += both * (xs[i] - xs[j]).abs().mean(-1)
                pairs += both
        seam = pairs > 0
        if not seam.any():  # near, cameras apart may leave a gap between their fields
            errors[d] = math.inf
            continue
        w = area * seam
        errors[d] = float((w * num / pairs.clamp(min=1)).sum() / w.sum())
    best = min(errors, key=errors.get)
    if math.isinf(errors[best]):
        raise ValueError("no two cameras of the rig see one grid point at any candidate "
                         "distance: there is no seam to choose a distance from")
    return best, errors
