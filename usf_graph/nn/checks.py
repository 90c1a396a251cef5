"""Measured equivariance on real grids: how much a network adds to interpolation error."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from ..cameras import Equirectangular

_A = np.array([0.3, -0.8, 0.5])


def smooth_signal(p: np.ndarray) -> np.ndarray:
    """A smooth analytic 3-channel test signal of unit vectors ``p [..., 3]``."""
    return np.stack([np.exp(p @ _A), np.cos(3 * p[..., 0]) * p[..., 1], p[..., 2] ** 2], -1)


def symmetry_permutation(pos: torch.Tensor, R: torch.Tensor, tol: float = 1e-9) -> torch.Tensor:
    """``sigma`` with ``R pos[i] = pos[sigma[i]]``, for a rotation ``R`` that maps the point
    set onto itself (e.g. the icosahedral group on icosahedral grids). A rotated signal is
    then ``x_rot[..., sigma, :] = x``. Raises ``ValueError`` if ``R`` is no such symmetry."""
    from ..geometry import rotate

    d = torch.cdist(rotate(pos, R), pos, compute_mode="donot_use_mm_for_euclid_dist")
    best = d.min(1)
    if best.values.max() >= tol:
        raise ValueError(f"R does not map the points onto themselves (worst miss "
                         f"{float(best.values.max()):.3g} >= {tol})")
    return best.indices


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

    from ..data.transforms import rotate_sample
    from ..frontend import GeometryCache, SphericalFrontend

    cam = Equirectangular(image_width, image_width // 2)
    rays, _ = cam.lens_normal_map()
    img = signal(rays)
    if img.ndim == 2:
        img = img[..., None]
    R = torch.as_tensor(R, dtype=torch.float64)
    cache = GeometryCache(None)
    x = SphericalFrontend(cam, grid, cache=cache).lift(img.astype(np.float64))
    rot_cam = cam.with_rotation(R.numpy() @ cam.rotation)
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
    from ..frontend import render

    cam = Equirectangular(width, width // 2)
    rays, _ = cam.lens_normal_map()
    R = torch.as_tensor(R, dtype=torch.float64)
    rot_cam = cam.with_rotation(R.numpy() @ cam.rotation)
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
    from .conv import SphericalConv
    from .graph import geodesic_radius_graph

    torch.manual_seed(seed)
    r = radius_spacings * grid.spacing
    ei, ew = geodesic_radius_graph(grid.pos, r)
    c1 = SphericalConv(channels[0], channels[1], r, num_basis=num_basis, basis=basis).double()
    c2 = SphericalConv(channels[1], channels[2], r, num_basis=num_basis, basis=basis).double()
    a = grid.area.double()
    return lambda x: c2(torch.tanh(c1(x, ei, ew, node_weight=a)), ei, ew, node_weight=a)
