"""The distance kernel, SphericalConv, pooling: equivariance, gradients, fast == reference."""

import math

import numpy as np
import pytest
import torch
from torch_geometric.nn import Sequential

from usf_graph import grids
from usf_graph.geometry import normalize, random_rotation, rotate, rotation_from_axis_angle
from usf_graph.grids import voronoi_areas
from usf_graph.nn import (
    DistanceKernel,
    GaussianPool,
    GridPool,
    GridUnpool,
    MaskedBatchNorm,
    SphericalConv,
    geodesic_radius_graph,
    global_mean_pool_area,
)
from usf_graph.nn.checks import symmetry_permutation


@pytest.fixture(autouse=True, scope="module")
def float64_default():
    """This module's checks run in float64; restored after, so other modules keep float32."""
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(old)


def random_sphere(n, seed):
    g = torch.Generator().manual_seed(seed)
    return normalize(torch.randn(n, 3, generator=g))


@pytest.mark.parametrize("basis", ["hat", "gaussian", "bessel", "mlp"])
def test_kernel_vanishes_at_radius_and_is_finite_at_zero(basis):
    k = DistanceKernel(5, 0.3, basis)
    d = torch.tensor([0.0, 0.1, 0.2999999, 0.3, 0.5])
    v = k(d)
    assert v.shape == (5, 5) and torch.isfinite(v).all()
    assert v[3:].abs().max() == 0 and v[2].abs().max() < 1e-4
    if basis == "hat":
        torch.testing.assert_close(v[:2].sum(1), torch.ones(2))


@pytest.mark.parametrize("kernel, basis", [("basis", "hat"), ("basis", "gaussian"),
                                           ("basis", "bessel"), ("mlp", "hat")])
def test_exact_so3_equivariance_on_point_sets(kernel, basis):
    pos = random_sphere(400, 0)
    x = torch.randn(400, 3, generator=torch.Generator().manual_seed(1))
    area = torch.as_tensor(voronoi_areas(pos.numpy()))
    conv = SphericalConv(3, 5, radius=0.35, num_basis=4, kernel=kernel, basis=basis)
    ei, ew = geodesic_radius_graph(pos, 0.35)
    y = conv(x, ei, ew, node_weight=area)
    for seed in range(3):
        R = random_rotation(seed=10 + seed)
        pr = rotate(pos, R)
        ei2, ew2 = geodesic_radius_graph(pr, 0.35)  # rebuilt from the rotated points
        y2 = conv(x, ei2, ew2, node_weight=torch.as_tensor(voronoi_areas(pr.numpy())))
        assert (y2 - y).abs().max() < 1e-10


def test_fast_path_matches_per_edge_reference_and_batched_form():
    pos = random_sphere(300, 2)
    ei, ew = geodesic_radius_graph(pos, 0.4)
    area = torch.as_tensor(voronoi_areas(pos.numpy()))
    mask = torch.rand(300, generator=torch.Generator().manual_seed(0)) > 0.3
    x = torch.randn(4, 300, 6, generator=torch.Generator().manual_seed(3))
    # 6 -> 7 mixes channels first, 2 -> 9 aggregates first (the narrower side)
    for normalize_, c_in, c_out in (("area", 6, 7), ("mean", 6, 7), (None, 6, 7),
                                    ("area", 2, 9), (None, 2, 9)):
        conv = SphericalConv(c_in, c_out, 0.4, num_basis=3, normalize=normalize_)
        x = x[..., :c_in]
        fast = conv(x, ei, ew, node_weight=area, mask=mask)
        ref = conv(x, ei, ew, node_weight=area, mask=mask, fast=False)
        assert (fast - ref).abs().max() < 1e-12
        for b in range(4):  # [B, N, C] == B separate [N, C] calls
            assert (conv(x[b], ei, ew, node_weight=area, mask=mask) - fast[b]).abs().max() < 1e-12
    # hidden points contribute nothing
    x2 = x.clone()
    x2[:, ~mask] = 1e6
    torch.testing.assert_close(conv(x2, ei, ew, node_weight=area, mask=mask),
                               conv(x, ei, ew, node_weight=area, mask=mask))


def test_naive_reference_by_hand():
    # three points, explicit formula
    pos = normalize(torch.tensor([[1.0, 0, 0], [1, 0.1, 0], [1, 0, 0.15]]))
    ei, ew = geodesic_radius_graph(pos, 0.5)
    conv = SphericalConv(1, 1, 0.5, num_basis=2, normalize="mean", bias=False)
    x = torch.tensor([[1.0], [2.0], [4.0]])
    y = conv(x, ei, ew)
    W = conv.weight.detach().view(2)
    phi = DistanceKernel(2, 0.5)
    for i in range(3):
        d = torch.stack([torch.atan2(torch.linalg.cross(pos[i], pos[j]).norm(), pos[i] @ pos[j])
                         for j in range(3)])
        p = phi(d)
        expect = (p * x).sum(0) @ W / p.sum()
        assert y[i, 0].item() == pytest.approx(expect.item(), rel=1e-12)


def test_gradcheck_including_self_loop():
    pos = random_sphere(40, 4)
    ei, ew = geodesic_radius_graph(pos, 0.8)
    assert (ew == 0).sum() == 40  # self-loops
    area = torch.as_tensor(voronoi_areas(pos.numpy()))
    x = torch.randn(2, 40, 2, requires_grad=True)
    conv = SphericalConv(2, 3, 0.8, num_basis=3, basis="gaussian")
    assert torch.autograd.gradcheck(lambda x: conv(x, ei, ew, node_weight=area), (x,))
    # the fast path's hand-written backward, for the input and the weight together
    W = conv.weight.detach().clone().requires_grad_(True)
    for xs in (x, x[0]):  # [B, N, C] and [N, C]
        assert torch.autograd.gradcheck(lambda x, W: torch.func.functional_call(
            conv, {"weight": W}, (x, ei, ew), {"node_weight": area}), (xs, W))
    wide = SphericalConv(2, 5, 0.8, num_basis=3, basis="gaussian")  # aggregates first
    W = wide.weight.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x, W: torch.func.functional_call(
        wide, {"weight": W}, (x, ei, ew), {"node_weight": area}), (x, W))
    w = ew.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda x, w: conv(x, ei, w, node_weight=area, fast=False), (x, w))
    mlp = SphericalConv(2, 2, 0.8, kernel="mlp", hidden=4)
    assert torch.autograd.gradcheck(lambda x, w: mlp(x, ei, w, node_weight=area), (x, w))


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


def test_masked_batchnorm_and_global_pool():
    x = torch.randn(3, 50, 4) * 5 + 2
    mask = torch.arange(50) < 30
    bn = MaskedBatchNorm(4)
    y = bn(x, mask)
    torch.testing.assert_close(y[:, mask].mean((0, 1)), torch.zeros(4), atol=1e-10, rtol=0)
    torch.testing.assert_close(y[:, mask].var((0, 1), unbiased=False), torch.ones(4), atol=1e-3, rtol=0)
    area = torch.rand(50)
    gm = global_mean_pool_area(x, area, mask)
    torch.testing.assert_close(gm, (x[:, mask] * area[mask, None]).sum(1) / area[mask].sum())


def test_pyg_conventions_sequential_repr_reset_compile():
    conv = SphericalConv(3, 8, 0.2, num_basis=4)
    assert repr(conv) == ("SphericalConv(3, 8, radius=0.2, num_basis=4, basis='hat', "
                          "normalize='area')")
    w0 = conv.weight.detach().clone()
    conv.reset_parameters()
    assert not torch.equal(w0, conv.weight)
    g = grids.icosahedral(2)
    ei, ew = geodesic_radius_graph(g.pos, 0.5)
    model = Sequential("x, ei, ew, a", [(SphericalConv(3, 4, 0.5), "x, ei, ew, a -> x"),
                                        torch.nn.ReLU(),
                                        (SphericalConv(4, 2, 0.5), "x, ei, ew, a -> x")])
    x = torch.randn(2, len(g), 3)
    y = model(x, ei, ew, g.area)
    assert y.shape == (2, len(g), 2)
    compiled = torch.compile(model, backend="eager")
    torch.testing.assert_close(compiled(x, ei, ew, g.area), y)


def test_bad_inputs():
    with pytest.raises(ValueError, match="normalize"):
        SphericalConv(1, 1, 0.1, normalize="sum")
    conv = SphericalConv(2, 2, 0.5)
    g = grids.icosahedral(1)
    ei, ew = geodesic_radius_graph(g.pos, 0.5)
    with pytest.raises(ValueError, match="node_weight"):
        conv(torch.randn(len(g), 2), ei, ew)
    with pytest.raises(ValueError, match="channels"):
        conv(torch.randn(len(g), 3), ei, ew, node_weight=g.area)
    with pytest.raises(ValueError, match="NaN"):
        geodesic_radius_graph(torch.full((5, 3), float("nan")), 0.1)


def test_radius_graph_is_not_truncated():
    g = grids.fibonacci(3000)
    ei, ew = geodesic_radius_graph(g.pos, 0.35)  # ~90 neighbours: above the first cap of 64
    deg = torch.bincount(ei[1])
    from scipy.spatial import cKDTree
    ref = [len(n) for n in cKDTree(g.pos.numpy()).query_ball_point(g.pos.numpy(), 2 * math.sin(0.35 / 2))]
    assert deg.tolist() == ref and int(deg.max()) > 64
    assert (ew <= 0.35).all() and (ei[1][1:] >= ei[1][:-1]).all()
    np.testing.assert_allclose(ew.numpy(), torch.atan2(
        torch.linalg.cross(g.pos[ei[0]], g.pos[ei[1]]).norm(dim=1),
        (g.pos[ei[0]] * g.pos[ei[1]]).sum(1)).numpy(), rtol=1e-12, atol=1e-15)
    assert (ew[ei[0] == ei[1]] == 0).all()


def test_euclidean_graphs_match_brute_force():
    from scipy.spatial import cKDTree

    from usf_graph.nn import euclidean_radius_graph, knn_graph

    gen = torch.Generator().manual_seed(0)
    pos = torch.cat([torch.randn(300, 3, generator=gen, dtype=torch.float64),
                     0.01 * torch.randn(100, 3, generator=gen, dtype=torch.float64)])  # a dense clump
    ei, ew = euclidean_radius_graph(pos, 0.3)
    tree = cKDTree(pos.numpy())
    ref = tree.query_ball_point(pos.numpy(), 0.3)
    assert torch.bincount(ei[1], minlength=len(pos)).tolist() == [len(n) for n in ref]
    assert max(len(n) for n in ref) > 100  # past the first neighbour cap: nothing truncated
    for i in (0, 350):
        assert sorted(ei[0][ei[1] == i].tolist()) == sorted(ref[i])
    torch.testing.assert_close(ew, (pos[ei[0]] - pos[ei[1]]).norm(dim=1), rtol=0, atol=0)
    ei, ew = knn_graph(pos[:300], 8)
    d, nb = cKDTree(pos[:300].numpy()).query(pos[:300].numpy(), k=8)
    assert (torch.bincount(ei[1]) == 8).all()
    for i in (0, 17, 299):
        assert sorted(ei[0][ei[1] == i].tolist()) == sorted(nb[i].tolist())
    np.testing.assert_allclose(np.sort(ew.reshape(300, 8).numpy(), 1), d, rtol=1e-12)
    with pytest.raises(ValueError, match="positive integer"):
        knn_graph(pos, 0)
    with pytest.raises(ValueError, match="NaN"):
        knn_graph(torch.full((5, 3), float("nan")), 2)


def test_tiled_fast_path_matches_the_reference(monkeypatch):
    # HEALPix nested numbering is a Z-order curve: row blocks reach narrow column windows
    import usf_graph.nn.conv as conv_module

    monkeypatch.setattr(conv_module, "TILE_ROWS", 64)
    g = grids.healpix(8)  # 768 points -> 12 tiles
    r = 1.6 * g.spacing
    ei, ew = geodesic_radius_graph(g.pos, r)
    j, i = ei
    coef = torch.ones(len(j), 1, dtype=torch.float64)
    tiles = conv_module.plan_tiles(i, j, coef, len(g))
    assert len(tiles) == 12 and sum(len(t[2]) for t in tiles) < 2 * len(g)
    shuffled = torch.randperm(len(g), generator=torch.Generator().manual_seed(0))
    assert len(conv_module.plan_tiles(shuffled[i], shuffled[j], coef, len(g))) == 1
    x = torch.randn(2, len(g), 3, generator=torch.Generator().manual_seed(1),
                    requires_grad=True)
    for c_out in (2, 7):  # mixing first and aggregating first
        conv = SphericalConv(3, c_out, r, num_basis=3, basis="gaussian")
        W = conv.weight.detach().clone().requires_grad_(True)
        f = lambda x, W, fast, conv=conv: torch.func.functional_call(  # noqa: E731
            conv, {"weight": W}, (x, ei, ew), {"node_weight": g.area, "fast": fast})
        fast, ref = f(x, W, True), f(x, W, False)
        assert (fast - ref).abs().max() < 1e-12
        go = torch.randn_like(fast)
        g_fast = torch.autograd.grad(fast, (x, W), go)
        g_ref = torch.autograd.grad(ref, (x, W), go)
        for a, b in zip(g_fast, g_ref):
            assert (a - b).abs().max() < 1e-12
        # an input that needs no gradient (a first layer): the weight's gradient alone
        (g_w,) = torch.autograd.grad(f(x.detach(), W, True), (W,), go)
        assert (g_w - g_ref[1]).abs().max() < 1e-12
