"""Grid pooling, unpooling and global readouts: values, masks, equivariance, PyG batches."""

import math

import pytest
import torch

from tests.helpers import random_sphere
from usf_graph import grids
from usf_graph.geometry import random_rotation, rotate, rotation_from_axis_angle
from usf_graph.nn import (
    GaussianPool,
    GridPool,
    GridUnpool,
    SphericalConv,
    geodesic_radius_graph,
)
from usf_graph.testing import symmetry_permutation


def _rz(k):
    return rotation_from_axis_angle(torch.tensor([0.0, 0, 1]), torch.tensor(k * math.pi / 2))


def test_conv_pool_conv_stack_is_equivariant_on_healpix():
    g = grids.healpix(8)
    with pytest.raises(ValueError, match="does not map the points"):  # 45 degrees: no symmetry
        symmetry_permutation(g.pos, rotation_from_axis_angle(torch.tensor([0.0, 0, 1]),
                                                             torch.tensor(math.pi / 4)))
    coarse, cl = g.coarsen()
    r1, r2 = 1.7 * g.spacing, 1.7 * coarse.spacing
    ei1, ew1 = geodesic_radius_graph(g.pos, r1)
    ei2, ew2 = geodesic_radius_graph(coarse.pos, r2)
    c1, c2 = SphericalConv(2, 4, r1), SphericalConv(4, 3, r2)
    for mode in ("max", "mean", "gaussian"):
        pool = GaussianPool(g.pos, coarse.pos, 0.5 * coarse.spacing, area=g.area) \
            if mode == "gaussian" else GridPool(cl, len(coarse), mode=mode, area=g.area)

        def net(x, pool=pool):
            h, m = pool(torch.relu(c1(x, ei1, ew1, node_weight=g.area)))
            return c2(h, ei2, ew2, node_weight=coarse.area)

        x = torch.randn(2, len(g), 2, generator=torch.Generator().manual_seed(5))
        for k in (1, 2, 3):
            R = _rz(k)
            s, sc = symmetry_permutation(g.pos, R), symmetry_permutation(coarse.pos, R)
            xr = torch.empty_like(x)
            xr[:, s] = x  # the rotated signal: (R f)(R p) = f(p)
            y, yr = net(x), net(xr)
            assert (yr[:, sc] - y).abs().max() < 1e-10


def test_pool_and_unpool_values():
    g = grids.icosahedral(2)
    coarse, cl = g.coarsen()
    x = torch.randn(len(g), 3)
    mask = torch.ones(len(g), dtype=torch.bool)
    mask[cl == 0] = False
    ymax, mc = GridPool(cl, len(coarse), "max")(x, mask)
    ymean, _ = GridPool(cl, len(coarse), "mean", area=g.area)(x, mask)
    for c in range(1, len(coarse)):
        sel = cl == c
        torch.testing.assert_close(ymax[c], x[sel].max(0).values)
        a = g.area[sel]
        torch.testing.assert_close(ymean[c], (x[sel] * a[:, None]).sum(0) / a.sum())
    assert not mc[0] and ymax[0].abs().sum() == 0
    up = GridUnpool(cl)(ymax)
    torch.testing.assert_close(up, ymax[cl])
    lin = GridUnpool(cl, "linear", g.pos, coarse.pos)(coarse.pos)  # linear in, near linear out
    assert (lin - g.pos).norm(dim=1).max() < 0.2
    torch.testing.assert_close(lin[:len(coarse)], coarse.pos)  # nested points are exact


def test_gaussian_pool_values_mask_and_rigid_invariance():
    fine, coarse = random_sphere(300, 1).double(), random_sphere(20, 2).double()
    area = torch.rand(300, dtype=torch.float64) + 0.5
    sigma = 0.3
    pool = GaussianPool(fine, coarse, sigma, area=area)
    x = torch.randn(2, 300, 3, dtype=torch.float64)
    mask = torch.rand(300) > 0.3
    y, mc = pool(x, mask)
    d = torch.atan2(torch.linalg.cross(coarse[:, None].expand(-1, 300, -1),
                                       fine[None].expand(20, -1, -1), dim=-1).norm(dim=-1),
                    coarse @ fine.T)
    w = torch.exp(-0.5 * (d / sigma) ** 2) * (d <= 3 * sigma) * area * mask
    ref = torch.einsum("cn,bnk->bck", w, x) / w.sum(1)[:, None]
    torch.testing.assert_close(y, ref, rtol=1e-12, atol=1e-12)
    assert mc.all()
    torch.testing.assert_close(pool(torch.ones(300, 2, dtype=torch.float64))[0],
                               torch.ones(20, 2, dtype=torch.float64))
    R = random_rotation(1, seed=3)[0].double()  # weights depend on distances only
    yr, _ = GaussianPool(rotate(fine, R), rotate(coarse, R), sigma, area=area)(x, mask)
    assert (yr - y).abs().max() < 1e-12
    far = GaussianPool(fine, -fine[:1], 1e-3)  # no fine point near the antipode
    assert not far(x)[1].any()
    with pytest.raises(ValueError, match="sigma"):
        GaussianPool(fine, coarse, 0.0)
