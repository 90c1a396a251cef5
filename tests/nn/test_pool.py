"""Grid pooling, unpooling and global readouts: values, masks, equivariance, PyG batches."""

import math

import pytest
import torch

from tests.helpers import random_sphere
from usf_graph import grids
from usf_graph.geometry import random_rotation, rotate, rotation_from_axis_angle
from usf_graph.nn import (
    FPSPool,
    GaussianPool,
    GridPool,
    GridUnpool,
    SphericalConv,
    geodesic_radius_graph,
    global_max_pool_masked,
    global_mean_pool_area,
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


_ICO = grids.icosahedral(2)


# (grid, whether its coarse points are among its points, a symmetry: axis and turns)
@pytest.mark.parametrize("grid, nested, axis, turns", [
    (_ICO, True, _ICO.pos[0].double(), 5),  # a fifth of a turn about a vertex
    (grids.healpix(4), False, torch.tensor([0.0, 0, 1], dtype=torch.float64), 4),
], ids=["ico", "healpix"])
def test_linear_unpool_blends_the_three_nearest_by_inverse_squared_distance(grid, nested, axis,
                                                                            turns):
    """Each fine point off the coarse grid: sum_i w_i x_i over its three nearest coarse
    points and those tied with the third (brute force), w_i proportional to 1 / |p - c_i|^2;
    and so it commutes with the grid's rotations (the tree's order broke the icosahedral
    grid's ties at the third place, 0.3-0.5 off)."""
    coarse, cl = grid.coarsen()
    x = torch.randn(len(coarse), 2, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    up = GridUnpool(cl, "linear", grid.pos, coarse.pos)
    got = up(x)
    d = torch.cdist(grid.pos.double(), coarse.pos.double())
    third = d.sort(1).values[:, 2:3]
    w = torch.where(d <= third * (1 + 1e-9), 1 / d.clamp_min(1e-300) ** 2, 0.0)
    want = (w / w.sum(1, keepdim=True)) @ x
    off = d.min(1).values > 1e-9
    assert off.sum() == len(grid) - (len(coarse) if nested else 0)
    torch.testing.assert_close(got[off], want[off], rtol=0, atol=1e-12)
    torch.testing.assert_close(got[~off], x[cl[~off]], rtol=0, atol=0)  # nested points: exact
    R = rotation_from_axis_angle(axis, torch.tensor(2 * math.pi / turns))
    s, sc = symmetry_permutation(grid.pos, R), symmetry_permutation(coarse.pos, R)
    xr = torch.empty_like(x)
    xr[sc] = x
    assert (up(xr)[s] - got).abs().max() < 1e-13


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


def _two_graphs(g, channels=3):
    """A PyG batch of two samples on grid ``g`` with different signals and masks."""
    from torch_geometric.data import Batch, Data

    gen = torch.Generator().manual_seed(11)
    datas = [Data(x=torch.randn(len(g), channels, generator=gen), pos=g.pos, area=g.area,
                  mask=torch.rand(len(g), generator=gen) > p) for p in (0.2, 0.6)]
    return datas, Batch.from_data_list(datas)


def test_pools_and_unpool_on_a_pyg_batch_equal_each_graph_alone():
    g = grids.healpix(4)
    coarse, cl = g.coarsen()
    datas, b = _two_graphs(g)
    pools = [GridPool(cl, len(coarse), "max"), GridPool(cl, len(coarse), "mean", area=g.area),
             GaussianPool(g.pos, coarse.pos, 0.5 * coarse.spacing, area=g.area)]
    for pool in pools:
        y, m, batch = pool(b.x, b.mask, batch=b.batch)
        assert batch.tolist() == [0] * len(coarse) + [1] * len(coarse)
        for i, d in enumerate(datas):
            yi, mi = pool(d.x, d.mask)
            assert torch.equal(m[batch == i], mi)
            assert (y[batch == i] - yi).abs().max() < 1e-14
        # one sample in the static form with a shared mask [N] gives that mask back as [M]
        y1, m1 = pool(datas[0].x[None], datas[0].mask)
        assert torch.equal(m1, m[batch == 0]) and (y1[0] - y[batch == 0]).abs().max() < 1e-14
        # the static form with per-sample masks [B, N] gives the same
        ys, ms = pool(b.x.view(2, len(g), -1), b.mask.view(2, len(g)))
        assert (ys.reshape(-1, 3) - y).abs().max() < 1e-14 and torch.equal(ms.reshape(-1), m)
    for up in (GridUnpool(cl), GridUnpool(cl, "linear", g.pos, coarse.pos)):
        xc = torch.randn(2 * len(coarse), 3)
        bc = torch.arange(2).repeat_interleave(len(coarse))
        y, batch = up(xc, batch=bc)
        for i in range(2):
            assert torch.equal(y[batch == i], up(xc[bc == i]))


def test_grid_layers_name_both_numbers_on_a_wrong_size():
    g = grids.healpix(4)
    coarse, cl = g.coarsen()
    pool = GridPool(cl, len(coarse))
    with pytest.raises(ValueError, match=f"x has 100 points .* grid of {len(g)}"):
        pool(torch.randn(100, 3))
    with pytest.raises(ValueError, match=f"grid of {len(g)} points, but the batch has graphs of"):
        pool(torch.randn(len(g) + 100, 3), batch=torch.cat([torch.zeros(len(g)),
                                                             torch.ones(100)]).long())
    with pytest.raises(ValueError, match="mask must have one value per point"):
        pool(torch.randn(2, len(g), 3), torch.ones(7, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"with batch, GridPool takes x \[sum N_i, C\] and batch \[sum N_i\]; "
                                         rf"got x \(1, {len(g)}, 3\)"):
        pool(torch.randn(1, len(g), 3), batch=torch.zeros(len(g), dtype=torch.long))
    with pytest.raises(ValueError, match=f"grid of {len(coarse)}"):
        GridUnpool(cl)(torch.randn(len(g), 3))


def test_readouts_on_a_pyg_batch_of_different_graphs():
    from torch_geometric.data import Batch, Data

    gen = torch.Generator().manual_seed(3)
    datas = [Data(x=torch.randn(n, 4, generator=gen), area=torch.rand(n, generator=gen) + 0.1,
                  mask=torch.rand(n, generator=gen) > 0.3) for n in (30, 55)]
    datas.append(Data(x=torch.randn(5, 4), area=torch.ones(5), mask=torch.zeros(5, dtype=torch.bool)))
    b = Batch.from_data_list(datas)
    gm = global_mean_pool_area(b.x, b.area, b.mask, batch=b.batch)
    gx = global_max_pool_masked(b.x, b.mask, batch=b.batch)
    for i, d in enumerate(datas[:2]):
        torch.testing.assert_close(gm[i], global_mean_pool_area(d.x, d.area, d.mask), rtol=1e-14, atol=1e-14)
        torch.testing.assert_close(gx[i], global_max_pool_masked(d.x, d.mask), rtol=0, atol=0)
        w = d.area * d.mask
        torch.testing.assert_close(gm[i], (d.x * w[:, None]).sum(0) / w.sum())
        torch.testing.assert_close(gx[i], d.x[d.mask].max(0).values)
    assert gm[2].abs().sum() == 0 and gx[2].abs().sum() == 0  # nothing visible: 0, not NaN
    assert gm.shape == gx.shape == (3, 4)  # one row per graph, as PyG's readouts
    with pytest.raises(ValueError, match=r"mask must have one value per point \(90\)"):
        global_max_pool_masked(b.x, b.mask.view(1, -1), batch=b.batch)  # a batch's mask is [sum N_i]
    # the static form: [B, N, C] with per-sample masks
    x, m = torch.randn(2, 30, 4), torch.rand(2, 30) > 0.5
    torch.testing.assert_close(global_mean_pool_area(x, None, m),
                               torch.stack([global_mean_pool_area(x[i], None, m[i]) for i in range(2)]))
    torch.testing.assert_close(global_max_pool_masked(x, m),
                               torch.stack([global_max_pool_masked(x[i], m[i]) for i in range(2)]))


def test_bad_arguments_are_refused_and_reprs_say_the_sizes():
    g = grids.icosahedral(2)
    coarse, cl = g.coarsen()
    for make, why in ((lambda: GridPool(cl, mode="sum"), "mode must be 'max' or 'mean', got 'sum'"),
                      (lambda: GridUnpool(cl, mode="cubic"),
                       "mode must be 'nearest' or 'linear', got 'cubic'"),
                      (lambda: GridUnpool(cl, mode="linear"),
                       "mode='linear' needs fine_pos and coarse_pos"),
                      (lambda: FPSPool(ratio=0), r"ratio in \(0, 1\] and radius > 0, got 0, 0.5"),
                      (lambda: FPSPool(radius=-1.0), r"radius > 0, got 0.25, -1.0")):
        with pytest.raises(ValueError, match=why):
            make()
    assert repr(GridPool(cl, mode="mean")) == "GridPool(162 -> 42, mode='mean')"
    assert repr(GridUnpool(cl)) == "GridUnpool(42 -> 162 points, mode='nearest')"
    assert repr(FPSPool(0.5, 0.2)) == "FPSPool(ratio=0.5, radius=0.2)"
    x = torch.rand(2, len(g), 3)
    with pytest.raises(ValueError, match=r"with batch, x must be \[sum N_i, C\] and batch "
                                         r"\[sum N_i\]; got \(2, 162, 3\) and \(324,\)"):
        global_mean_pool_area(x, batch=torch.zeros(2 * len(g), dtype=torch.long))
