"""Equivariance assertions for layers and models, and measured equivariance on real grids.

* :func:`assert_equivariant`: a rotation that maps a point set onto itself permutes the
  points; a layer on that point set must commute with the permutation (per-point
  outputs) or ignore it (invariant outputs). Exact up to rounding, for any layer or model.
* :func:`assert_motion_invariant`: a layer that builds its geometry from positions must
  give the same per-point (or global) features for the rotated (and translated) points.
* :func:`grid_equivariance_error` and friends measure how much a network adds to the
  interpolation error under rotations that are not grid symmetries.

Modelled on e3nn's ``assert_equivariant``. Default tolerances (relative to the output's
largest magnitude): 1e-10 in float64 and 1e-5 in float32.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from .cameras import Equirectangular
from .geometry import random_rotation, rotate

_A = np.array([0.3, -0.8, 0.5])


def smooth_signal(p: np.ndarray) -> np.ndarray:
    """A smooth analytic 3-channel test signal of unit vectors ``p [..., 3]``."""
    return np.stack([np.exp(p @ _A), np.cos(3 * p[..., 0]) * p[..., 1], p[..., 2] ** 2], -1)


def symmetry_permutation(pos: torch.Tensor, R: torch.Tensor, tol: float = 1e-9) -> torch.Tensor:
    """``sigma`` with ``R pos[i] = pos[sigma[i]]``, for a rotation ``R`` that maps the point
    set onto itself (e.g. the icosahedral group on icosahedral grids). A rotated signal is
    then ``x_rot[..., sigma, :] = x``. Raises ``ValueError`` if ``R`` is no such symmetry."""
    d = torch.cdist(rotate(pos, R), pos, compute_mode="donot_use_mm_for_euclid_dist")
    best = d.min(1)
    if best.values.max() >= tol:
        raise ValueError(f"R does not map the points onto themselves (worst miss "
                         f"{float(best.values.max()):.3g} >= {tol})")
    return best.indices


TOLERANCE = {torch.float64: 1e-10, torch.float32: 1e-5}


def _tolerance(out, atol):
    if atol is not None:
        return float(atol)
    return TOLERANCE.get(out.dtype, 1e-3)


def _as_tuple(v):
    return tuple(v) if isinstance(v, (tuple, list)) else (v,)


def _permute(t: torch.Tensor, sigma: torch.Tensor, dim: int) -> torch.Tensor:
    """The signal turned by the symmetry: ``out[..., sigma[i], ...] = t[..., i, ...]``."""
    inv = torch.empty_like(sigma)
    inv[sigma] = torch.arange(len(sigma), device=sigma.device)
    return t.index_select(dim, inv.to(t.device))


def _compare(outs, refs, atol) -> float:
    worst = 0.0
    for o, r in zip(outs, refs):
        if o.shape != r.shape:
            raise AssertionError(f"output shapes differ: {tuple(o.shape)} vs {tuple(r.shape)}")
        o, r = o.detach(), r.detach()
        if o.dtype == torch.bool or not o.is_floating_point():
            if not torch.equal(o, r):
                raise AssertionError("a discrete output (mask, labels) does not follow the "
                                     "rotation")
            continue
        scale = max(float(r.abs().max()) if r.numel() else 0.0, 1e-30)
        err = float((o - r).abs().max()) / scale if r.numel() else 0.0
        tol = _tolerance(r, atol)
        if not err <= tol:
            raise AssertionError(f"not equivariant: max error {err:.3g} (relative to the "
                                 f"output's scale {scale:.3g}) > tolerance {tol:.3g}")
        worst = max(worst, err)
    return worst


def assert_equivariant(fn: Callable, args, pos: torch.Tensor, rotation: torch.Tensor, *,
                       in_dims=None, out_pos: torch.Tensor | None = None, out_dims=None,
                       invariant: bool = False, atol: float | None = None) -> float:
    r"""Assert ``fn(g . args) == g . fn(args)`` for the rotation ``g`` that maps the points
    ``pos [N, 3]`` (and ``out_pos``) onto themselves.

    A symmetry turns a signal by permuting points: the value at :math:`p_i` moves to
    :math:`R p_i = p_{\sigma(i)}`. Each input in ``args`` (a tensor or a tuple) is permuted
    along its point dimension (``in_dims``; default ``-2`` for tensors of 2 or more
    dimensions, ``-1`` for 1-D ones such as masks and areas; ``None`` leaves an input
    alone). Each output is permuted on ``out_pos`` (default ``pos``; a pool's coarse grid)
    along ``out_dims`` (default ``-2``, ``-1`` for 1-D outputs; an entry ``None``: that
    output must be invariant). ``invariant=True``: every output must be invariant (logits,
    global readouts). Returns the largest relative error; raises
    ``AssertionError`` above ``atol`` (default :data:`TOLERANCE` for the output dtype)
    and ``ValueError`` when ``rotation`` is not a symmetry of the points.
    """
    args = _as_tuple(args)
    sigma = symmetry_permutation(pos, rotation)
    sigma_out = sigma if out_pos is None else symmetry_permutation(out_pos, rotation)

    def default(t):
        return None if not isinstance(t, torch.Tensor) else -1 if t.dim() == 1 else -2

    in_dims = [default(a) for a in args] if in_dims is None else list(in_dims)
    turned = [a if d is None else _permute(a, sigma, d) for a, d in zip(args, in_dims)]
    with torch.no_grad():
        outs, outs_r = _as_tuple(fn(*args)), _as_tuple(fn(*turned))
    if invariant:
        out_dims = [None] * len(outs)
    elif out_dims is None:
        out_dims = [default(o) for o in outs]
    elif not isinstance(out_dims, (tuple, list)):
        out_dims = [out_dims] * len(outs)
    refs = [o if d is None else _permute(o, sigma_out, d) for o, d in zip(outs, out_dims)]
    return _compare(outs_r, refs, atol)


def assert_motion_invariant(fn: Callable, pos: torch.Tensor, args=(),
                            rotation: torch.Tensor | None = None,
                            translation: torch.Tensor | None = None, *,
                            atol: float | None = None) -> float:
    """Assert ``fn(R pos + t, *args) == fn(pos, *args)``: a layer or model that builds
    its geometry from positions gives the same features (per point, in the same order, or
    global) for moved points. ``rotation`` defaults to a fixed generic rotation; use no
    ``translation`` on S2. Returns the largest relative error (see
    :func:`assert_equivariant`)."""
    R = random_rotation(generator=torch.Generator().manual_seed(7)) if rotation is None \
        else torch.as_tensor(rotation)
    moved = rotate(pos, R.to(pos.dtype))
    if translation is not None:
        moved = moved + torch.as_tensor(translation, dtype=pos.dtype)
    args = _as_tuple(args)
    with torch.no_grad():
        return _compare(_as_tuple(fn(moved, *args)), _as_tuple(fn(pos, *args)), atol)


def _rel(a: torch.Tensor, b: torch.Tensor, w: torch.Tensor) -> float:
    """Weighted relative L2 error ||a - b|| / ||b||; ``w`` per point (areas)."""
    w = w.reshape(-1, *([1] * (a.dim() - 1)))
    return float(((w * (a - b) ** 2).sum() / (w * b ** 2).sum()).sqrt())


def grid_equivariance_error(net: Callable[[torch.Tensor], torch.Tensor], grid,
                            signal: Callable[[np.ndarray], np.ndarray], R: torch.Tensor,
                            image_width: int = 1024) -> dict:
    r"""Lift ``signal`` and ``signal`` rotated by ``R`` onto ``grid`` through an
    equirectangular camera and compare ``net(lift(f o R^T))`` with ``net(lift(f))`` turned
    by ``R`` (barycentric grid-to-grid resampling, :func:`~usf_graph.data.rotate_sample`).

    Returns ``{"interpolation": e0, "network": e1, "ratio": e1 / e0}``: ``e0`` is the same
    comparison for the identity network, the error the sampling alone makes, so ``ratio``
    says how much the network adds. ``net`` maps ``[N, C]`` float64 to ``[N, C']``.
    """
    from torch_geometric.data import Data

    from .data.transforms import rotate_sample
    from .frontend import GeometryCache, SphericalFrontend

    cam = Equirectangular(image_width, image_width // 2)
    rays, _ = cam.lens_normal_map()
    img = signal(rays)
    if img.ndim == 2:
        img = img[..., None]
    R = torch.as_tensor(R, dtype=torch.float64)
    cache = GeometryCache(None)
    x = SphericalFrontend(cam, grid, cache=cache).lift(img.astype(np.float64))
    rot_cam = cam.turned(R.numpy())
    x_r = SphericalFrontend(rot_cam, grid, cache=cache).lift(img.astype(np.float64))
    area = grid.area.double()
    with torch.no_grad():
        y, y_r = net(x), net(x_r)
        # input and output turned together: one triangulation for both
        both = rotate_sample(Data(x=torch.cat([x, y], -1), pos=grid.pos), R).x
    e0 = _rel(x_r, both[:, :x.shape[1]], area)
    e1 = _rel(y_r, both[:, x.shape[1]:], area)
    return {"interpolation": e0, "network": e1, "ratio": e1 / e0}


def equirect_equivariance_error(net: Callable[[torch.Tensor], torch.Tensor],
                                signal: Callable[[np.ndarray], np.ndarray], R: torch.Tensor,
                                width: int = 128) -> dict:
    """The same protocol for a planar network on the equirectangular image ``[1, C, H, W]``:
    the rotated image is re-rendered from the signal, and the output is turned by
    re-rendering it through the rotated camera. Errors weighted by cos(latitude)."""
    from .frontend import render

    cam = Equirectangular(width, width // 2)
    rays, _ = cam.lens_normal_map()
    R = torch.as_tensor(R, dtype=torch.float64)
    rot_cam = cam.turned(R.numpy())
    img = np.atleast_3d(signal(rays)).astype(np.float64)
    img_r = np.atleast_3d(signal(rays @ R.numpy()))  # f(R^T p)

    def turn(a):  # [H, W, C] numpy: the picture seen by the rotated camera
        return np.atleast_3d(render(a, rot_cam, cam))

    def run(a):
        t = torch.from_numpy(np.ascontiguousarray(a)).permute(2, 0, 1)[None]
        with torch.no_grad():
            return net(t)[0].permute(1, 2, 0).numpy()

    wlat = torch.from_numpy(np.hypot(rays[..., 0], rays[..., 1])).reshape(-1)  # cos(lat)
    flat = lambda a: torch.from_numpy(np.ascontiguousarray(a)).reshape(len(wlat), -1)  # noqa: E731
    e0 = _rel(flat(img_r), flat(turn(img)), wlat)
    e1 = _rel(flat(run(img_r)), flat(turn(run(img))), wlat)
    return {"interpolation": e0, "network": e1, "ratio": e1 / e0}


def random_spherical_net(grid, radius_spacings: float = 4.0, num_basis: int = 3,
                         basis: str = "gaussian", channels=(3, 16, 8), seed: int = 0):
    """A 2-layer SphericalConv network (tanh between) with seeded random float64 weights on
    ``grid``, as a function ``[N, C] -> [N, C']``: the probe of the equivariance checks."""
    from .graph import geodesic_radius_graph
    from .nn import SphericalConv

    torch.manual_seed(seed)
    r = radius_spacings * grid.spacing
    ei, ew = geodesic_radius_graph(grid.pos, r)
    a = grid.area.double()
    c1, c2 = (SphericalConv(ci, co, r, num_basis=num_basis, basis=basis).double()
              .bind(ei, ew, node_weight=a) for ci, co in zip(channels[:-1], channels[1:]))
    return lambda x: c2(torch.tanh(c1(x)))
