"""SphericalFrontend: camera + grid -> SphericalImage, with all geometry cached."""

from __future__ import annotations

import hashlib
import sys

import numpy as np
import torch
from scipy.spatial import cKDTree

from ..cameras import Camera
from ..graph import check_radius, geodesic_radius_graph
from ..grids import Grid
from ..sparse import csr_indices, quiet_sparse
from .cache import GeometryCache, default_cache
from .image import SphericalImage
from .interpolation import (
    build_table,
    check_method,
    valid_pixels,
)
from .remap import Remap


def default_radius(grid: Grid) -> float:
    """About 1.6 grid spacings: the centre and its ~6 nearest neighbours."""
    return 1.6 * grid.spacing


def grid_graph(grid: Grid, radius: float, cache: GeometryCache | None = None):
    """The geodesic radius graph of a grid, ``(edge_index, edge_weight)``, from ``cache``
    (default: the process-wide one), built once per (grid, radius)."""
    radius = float(radius)
    g = (cache if cache is not None else default_cache()).get(
        "graph", {"grid": grid.key(), "radius": radius},
        lambda: dict(zip(("edge_index", "edge_weight"), geodesic_radius_graph(grid.pos, radius))))
    return g["edge_index"], g["edge_weight"]


class _Table:
    """A row-normalized sparse interpolation matrix, applied as a gather when rows are
    regular (bilinear/nearest) and as a sparse matmul otherwise."""

    def __init__(self, crow, col, val, n_cols):
        self.n_rows, self.n_cols = len(crow) - 1, n_cols
        self.parts = tuple(torch.as_tensor(a) for a in (crow, col, val))
        counts = torch.diff(torch.as_tensor(crow))
        self.regular = bool(counts.numel()) and bool((counts == counts[0]).all())
        if self.regular:
            p = int(counts[0])
            self.idx = torch.as_tensor(col).reshape(-1, p)
            self.w = torch.as_tensor(val).reshape(-1, p)
        else:
            with quiet_sparse():
                idx = csr_indices(torch.as_tensor(crow), torch.as_tensor(col), n_cols)
                self.csr = torch.sparse_csr_tensor(*idx, torch.as_tensor(val),
                                                   (self.n_rows, n_cols))

    def apply(self, flat: torch.Tensor, rows: slice | None = None) -> torch.Tensor:
        """``flat [..., n_cols, C]`` -> ``[..., n_rows, C]`` (only ``rows`` of them)."""
        if self.regular:
            idx, w = (self.idx, self.w) if rows is None else (self.idx[rows], self.w[rows])
            g = flat[..., idx, :]  # [..., rows, P, C]
            return (g * w.to(flat.dtype)[..., None]).sum(-2)
        lead, c = flat.shape[:-2], flat.shape[-1]
        # the sparse matmul has no half-precision kernels on CPU: those in float32
        work = flat.dtype if flat.dtype in (torch.float32, torch.float64) else torch.float32
        x = flat.movedim(-2, 0).reshape(self.n_cols, -1).to(work)
        out = (self.csr.to(work) @ x).reshape(self.n_rows, *lead, c).to(flat.dtype)
        return (out if rows is None else out[rows]).movedim(0, -2)


def _as_image(image, cam: Camera, batched: bool = False):
    is_np = not isinstance(image, torch.Tensor)
    arr = np.asarray(image) if is_np else image
    nd = 3 if batched else 2
    if arr.ndim == nd:
        arr = arr[..., None]
    hw = tuple(arr.shape[-3:-1])
    if arr.ndim != nd + 1 or hw != (cam.height, cam.width):
        want = "[B, H, W, C]" if batched else "[H, W] or [H, W, C]"
        raise ValueError(f"image has shape {tuple(np.shape(image))} but the camera expects "
                         f"{want} with H x W = {cam.height} x {cam.width}. Use the camera "
                         "calibrated for this resolution, or, for images resized as a whole, "
                         "camera.resized(W, H) (the command line does it when the aspect "
                         "ratio matches).")
    if arr.shape[-1] == 0:
        raise ValueError(f"image has shape {tuple(np.shape(image))}: no channels to lift")
    return arr, is_np


def _digest(a) -> str | None:
    if a is None:
        return None
    return hashlib.sha256(np.ascontiguousarray(np.asarray(a, bool)).tobytes()).hexdigest()[:16]


class SphericalFrontend:
    r"""Lifts images from one camera onto one grid on S2.

    Args:
        camera: any :mod:`usf_graph.cameras` model.
        grid: a :class:`~usf_graph.grids.Grid`.
        interpolation: ``bilinear`` | ``nearest`` | ``area`` (anti-aliased, for grids
            coarser than the image) | ``rbf`` (Gaussian weights of the lifted pixels).
        radius: geodesic radius (rad) of the graph edges; default about 1.6 spacings.
        image_mask: optional ``[H, W]`` bool, False on pixels to ignore (vignetting,
            the robot's body); combined with the camera's own :attr:`~Camera.image_mask`.
        cache: a :class:`GeometryCache`; defaults to the process-wide one.
        rbf_sigma: the Gaussian's width (rad) for ``rbf``: each point averages the pixels
            whose rays lie within 3 sigma of it, weighted by exp(-d^2 / 2 sigma^2);
            default half the grid's spacing.

    The interpolation table, field-of-view mask and radius graph depend only on the
    camera and the grid: they are built once and cached in memory and on disk. Lifting a
    sample is then one ``cv2.remap`` (numpy uint8/uint16/float32 images, bilinear or
    nearest) or one gather / sparse matmul in float64-exact weights (everything else).
    """

    def __init__(self, camera: Camera, grid: Grid, interpolation: str = "bilinear",
                 radius: float | None = None, image_mask=None,
                 cache: GeometryCache | None = None, rbf_sigma: float | None = None):
        check_method(interpolation)  # before the cache announces a build
        self.camera, self.grid, self.interpolation = camera, grid, interpolation
        self.cache = cache if cache is not None else default_cache()
        if image_mask is not None and np.shape(image_mask) != (camera.height, camera.width):
            raise ValueError(f"image_mask must have shape {(camera.height, camera.width)}, "
                             f"got {np.shape(image_mask)}")
        if camera.image_mask is not None:  # the camera's own mask (from its file) applies too
            image_mask = camera.image_mask if image_mask is None else \
                camera.image_mask & np.asarray(image_mask, bool)
        key = {"camera": camera.key(), "grid": grid.key(), "interpolation": interpolation,
               "image_mask": _digest(image_mask), "rbf_sigma": rbf_sigma}

        def build():
            _say(f"building lift table {interpolation}: {camera.model} "
                 f"{camera.width}x{camera.height} -> {grid.spec} ({len(grid)} points)")
            return build_table(camera, grid.pos.numpy(), interpolation, image_mask, rbf_sigma,
                               grid.spacing if interpolation == "rbf" else None)

        t = self.cache.get("lift", key, build)
        self._image_mask, self._rows = image_mask, (t["crow"], t["col"], t["val"])
        self.mask = t["mask"].bool()
        self._table = _Table(t["crow"], t["col"], t["val"], camera.width * camera.height)
        self._uv = t["uv"].numpy()
        # checked now: the graph is built on first use, and a lifted file records the radius
        self.radius = check_radius(radius) if radius is not None else default_radius(grid)
        self._edges = None  # built on first use: lift/lift_batch never need the graph
        self._fast = None
        self._render = {}

    @property
    def edge_index(self) -> torch.Tensor:
        """``[2, E]`` radius graph of the grid (row 0 neighbour, row 1 centre), cached."""
        return self._graph()[0]

    @property
    def edge_weight(self) -> torch.Tensor:
        """``[E]`` geodesic length of each edge (radians)."""
        return self._graph()[1]

    def _graph(self):
        if self._edges is None:
            self._edges = grid_graph(self.grid, self.radius, self.cache)
        return self._edges

    @property
    def num_points(self) -> int:
        """N: the grid's number of points (visible or not)."""
        return len(self.grid)

    def __repr__(self) -> str:
        return (f"SphericalFrontend({self.camera!r}, {self.grid!r}, interpolation="
                f"'{self.interpolation}', radius={self.radius:.4g}, visible={int(self.mask.sum())})")

    # -- lifting -----------------------------------------------------------------------
    def _remap(self) -> Remap:
        """The ``cv2.remap`` fast path of :meth:`lift`, built on first use."""
        if self._fast is None:
            self._fast = Remap(self.camera, self._uv, self.mask.numpy(), self.interpolation,
                               valid_pixels(self.camera, self._image_mask))
        return self._fast

    def lift(self, image) -> torch.Tensor:
        """One image ``[H, W]`` or ``[H, W, C]`` (numpy or torch) -> ``[N, C]`` float32
        (float64 stays float64). Points outside the field of view are 0."""
        arr, is_np = _as_image(image, self.camera)
        if is_np and self.interpolation in ("bilinear", "nearest") and Remap.accepts(arr):
            x = torch.from_numpy(self._remap()(arr))
            if arr.dtype.kind != "f":
                return x  # integer pixels cannot be NaN
        else:
            t = torch.as_tensor(arr)
            if not t.is_floating_point():
                t = t.float()
            x = self._table.apply(t.reshape(-1, t.shape[-1]))
        _check_finite(x, self.mask)
        return x

    def lift_batch(self, images) -> torch.Tensor:
        """``[B, H, W, C]`` (or ``[B, H, W]``) -> ``[B, N, C]``, the static-graph fast path."""
        arr, _ = _as_image(images, self.camera, batched=True)
        t = torch.as_tensor(arr)
        if not t.is_floating_point():
            t = t.float()
        x = self._table.apply(t.reshape(t.shape[0], -1, t.shape[-1]))
        _check_finite(x, self.mask)
        return x

    def lift_table(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The lifting as a CSR matrix ``[N, H W]``, ``(crow, col, val)``: grid point i
        is the sum over its entries of ``val`` times pixel ``col`` (row-major), 0 outside
        the field of view. What :meth:`lift` applies (``cv2.remap`` computes the same)."""
        return self._table.parts

    def render_table(self, mode: str = "nearest") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`to_image`'s ``mode`` as a CSR matrix ``[H W, N]``, ``(crow, col, val)``:
        pixels without a ray have weight 0."""
        if mode not in ("bilinear", "nearest"):
            raise ValueError(f"mode must be 'bilinear' or 'nearest', got {mode!r}")
        return self._renderer(mode).parts

    def __call__(self, image) -> SphericalImage:
        return self.image(self.lift(image))

    def image(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> SphericalImage:
        """The :class:`SphericalImage` of lifted values ``x [N, C]`` on this grid, with the
        cached graph (``mask``: default, the camera's field of view)."""
        mask = self.mask if mask is None else mask
        return SphericalImage.on_grid(x, self.grid, mask.clone(), self.edge_index,
                                      self.edge_weight)

    # -- back to pixels ------------------------------------------------------------------
    def to_image(self, values, mode: str = "bilinear"):
        """Per-point values ``[N]`` or ``[N, C]`` -> the camera's image ``[H, W(, C)]``.

        ``bilinear`` blends the three nearest visible grid points by inverse squared
        (chordal) distance; ``nearest`` copies the nearest one (use it for labels). Pixels
        without a ray are 0.
        """
        if mode not in ("bilinear", "nearest"):
            raise ValueError(f"mode must be 'bilinear' or 'nearest', got {mode!r}")
        is_np = not isinstance(values, torch.Tensor)
        v = torch.as_tensor(np.asarray(values) if is_np else values)
        squeeze = v.ndim == 1
        v = v[:, None] if squeeze else v
        if v.shape[0] != self.num_points:
            raise ValueError(f"values have {v.shape[0]} points, the grid has {self.num_points}")
        if v.is_floating_point():
            self._check_seen_finite(v, "values")
            out = self._renderer(mode).apply(v)
        else:
            out = self._renderer(mode).apply(v.double()).round().to(v.dtype)
        out = out.reshape(self.camera.height, self.camera.width, -1)
        out = out[..., 0] if squeeze else out
        return out.numpy() if is_np else out

    def to_labels(self, scores: torch.Tensor, mode: str = "nearest",
                  chunk: int = 1 << 16) -> torch.Tensor:
        """Per-point class scores ``[N, C]`` (probabilities) -> labels ``[H, W]`` (int64)
        in the camera's pixels (0 where it has no ray).

        ``nearest``: each pixel takes the label of the nearest visible point (the scores'
        argmax there). ``soft``: the argmax of the scores blended as :meth:`to_image`'s
        ``bilinear``, so that on images finer than the grid a boundary runs between the
        points instead of along their Voronoi cells. Blending probabilities, not labels,
        is what makes it well defined. Pixels are taken ``chunk`` at a time, so a large
        image never holds ``[H, W, C]`` scores."""
        if mode not in ("nearest", "soft"):
            raise ValueError(f"mode must be 'nearest' or 'soft', got {mode!r}")
        if scores.dim() != 2 or scores.shape[0] != self.num_points:
            raise ValueError(f"scores must be [{self.num_points}, C], got {tuple(scores.shape)}")
        if mode == "nearest":
            return self.to_image(scores.argmax(-1), mode="nearest")
        self._check_seen_finite(scores, "scores")
        table = self._renderer("bilinear")
        out = torch.empty(table.n_rows, dtype=torch.long)
        for s in range(0, table.n_rows, chunk):
            out[s:s + chunk] = table.apply(scores, rows=slice(s, s + chunk)).argmax(-1)
        return out.reshape(self.camera.height, self.camera.width)

    def _check_seen_finite(self, v: torch.Tensor, what: str) -> None:
        """Refuse NaN or inf at the points the camera sees (``v [N, C]``); hidden points are
        never read, so they may hold anything."""
        bad = int((~torch.isfinite(v[self.mask.to(v.device)])).any(-1).sum())
        if bad:
            raise ValueError(f"{what} have NaN or inf at {bad} grid points the camera sees; "
                             "they would spread into the image")

    def _renderer(self, mode: str) -> _Table:
        """The render table of ``mode``, built once per camera, grid and field of view."""
        if mode not in self._render:
            key = {"camera": self.camera.key(), "grid": self.grid.key(), "mode": mode,
                   "mask": _digest(self.mask.numpy())}
            t = self.cache.get("render", key, lambda: _render_table(self, mode))
            self._render[mode] = _Table(t["crow"], t["col"], t["val"], self.num_points)
        return self._render[mode]


def _render_table(fe: SphericalFrontend, mode: str) -> dict:
    cam = fe.camera
    rays, valid = cam.lens_normal_map()
    rays, valid = rays.reshape(-1, 3), valid.ravel()
    vis = np.flatnonzero(fe.mask.numpy())
    k = 1 if mode == "nearest" else 3
    d, j = cKDTree(fe.grid.pos.numpy()[vis]).query(np.where(valid[:, None], rays, 1.0), k=k)
    d, j = d.reshape(len(rays), k), j.reshape(len(rays), k)
    w = 1.0 / np.maximum(d, 1e-12) ** 2
    w = np.where(valid[:, None], w / w.sum(1, keepdims=True), 0.0)
    crow = np.arange(0, len(rays) * k + 1, k)
    return {"crow": crow, "col": vis[j].ravel(), "val": w.ravel()}


def _check_finite(x: torch.Tensor, mask: torch.Tensor) -> None:
    if not x.is_floating_point():
        return
    # numpy's isfinite is one SIMD pass; torch's isfinite().all() wakes its thread pool
    # and cost ~2x a cv2.remap of the same points (benchmarks/lift.py)
    fast = x.device.type == "cpu" and x.dtype in (torch.float32, torch.float64)
    if bool(np.isfinite(x.detach().numpy()).all() if fast else torch.isfinite(x).all()):
        return  # the masked check only on failure
    if not torch.isfinite(x[..., mask, :]).all():
        raise ValueError("the image has NaN or inf in pixels the camera sees; clean them, or "
                         "mask them: image_mask= in Python, --image-mask on the command line")


def _say(msg: str) -> None:
    print(f"[usf-graph] {msg}", file=sys.stderr, flush=True)
