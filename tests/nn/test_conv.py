"""SphericalConv / PointConv: an independent dense reference, never-stale geometry,
gradients everywhere, equivariance through the harness, PyG conventions."""

import functools
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch_geometric.nn import Sequential

from tests.helpers import random_sphere
from usf_graph import grids
from usf_graph.geometry import rotation_from_axis_angle
from usf_graph.grids import voronoi_areas
from usf_graph.nn import (
    EdgePlan,
    PointConv,
    SphericalConv,
    UprightConv,
    aggregate,
    geodesic_radius_graph,
    knn_graph,
)
from usf_graph.testing import assert_equivariant, assert_motion_invariant, symmetry_permutation


def dense_reference(x, pos, conv, node_weight=None, mask=None, euclidean=False):
    """The layer's formula from positions alone: every pair of points, its distance, the
    basis written out here (hat, gaussian or bessel), a dense sum. Shares no code with the
    layer beyond reading its weights."""
    a = dense_coefficients(pos, conv, node_weight, mask, euclidean)
    W = conv.weight.view(conv.num_basis, conv.in_channels, conv.out_channels)
    y = torch.einsum("ijk,...jc,kco->...io", a, x, W)
    return y + conv.bias if conv.bias is not None else y


def dense_coefficients(pos, conv, node_weight=None, mask=None, euclidean=False):
    """The normalized coefficients a_ijk of every pair of points ``[N_i, N_j, K]``."""
    K, r = conv.num_basis, conv.radius
    if euclidean:
        d = (pos[:, None] - pos[None]).norm(dim=-1)
    else:
        d = torch.atan2(torch.linalg.cross(pos[:, None].expand(-1, len(pos), -1),
                                           pos[None].expand(len(pos), -1, -1), dim=-1).norm(dim=-1),
                        pos @ pos.T)
    u = (d / r)[..., None]
    k = torch.arange(K, dtype=d.dtype)
    env = 1 - u.clamp(0, 1) ** 3 * (10 - 15 * u.clamp(0, 1) + 6 * u.clamp(0, 1) ** 2)
    if conv.kernel.basis == "hat":
        phi = torch.relu(1 - (u * K - k).abs())
    elif conv.kernel.basis == "gaussian":
        c = k / max(K - 1, 1)
        phi = torch.exp(-0.5 * ((u - c) * K) ** 2) * env
    elif conv.kernel.basis == "bessel":  # sqrt(2/r) sin(n pi d / r) / d, n pi / r at d = 0
        n = (k + 1) * math.pi / r
        dd = d[..., None]
        wave = torch.where(dd > 0, torch.sin(n * dd) / dd.clamp_min(1e-300), n)
        phi = math.sqrt(2 / r) * wave * env
    else:
        raise NotImplementedError(conv.kernel.basis)
    inside = (d < r)[..., None]
    phi = phi * inside  # [N_i, N_j, K]
    # signed bases could sum to 0 at a point: they are normalized by the envelope instead
    mass = phi.sum(-1) if conv.kernel.basis != "bessel" else (env * inside)[..., 0]
    w = torch.ones(len(pos), dtype=d.dtype)
    if conv.normalize == "area" and node_weight is not None:
        w = node_weight.to(d.dtype)
    if mask is not None:
        w = w * mask.to(d.dtype)
    a = phi * w[None, :, None]
    if conv.normalize is not None:
        a = a / (mass * w[None]).sum(1).clamp_min(1e-12)[:, None, None]
    return a


def graph(pos, r):
    ei, ew = geodesic_radius_graph(pos, r)
    return ei, ew, torch.as_tensor(voronoi_areas(pos.numpy()))


@pytest.mark.parametrize("normalize, c_in, c_out, basis", [
    ("area", 6, 7, "hat"), ("mean", 6, 7, "hat"), (None, 6, 7, "hat"), ("area", 2, 9, "hat"),
    (None, 2, 9, "hat"), ("area", 6, 7, "bessel"), ("mean", 2, 9, "bessel")])
def test_every_path_equals_the_dense_reference(normalize, c_in, c_out, basis):
    # 6 -> 7 mixes channels first, 2 -> 9 aggregates first (the narrower side)
    pos = random_sphere(300, 2)
    ei, ew, area = graph(pos, 0.4)
    area[:5] = 0.0  # areas may be 0 (a point of no extent)
    mask = torch.rand(300, generator=torch.Generator().manual_seed(0)) > 0.3
    x = torch.randn(4, 300, c_in, generator=torch.Generator().manual_seed(3))
    conv = SphericalConv(c_in, c_out, 0.4, num_basis=3, normalize=normalize, basis=basis)
    with torch.no_grad():  # a bias of zeros (its initialization) would pass unadded
        conv.bias.normal_(generator=torch.Generator().manual_seed(4))
    ref = dense_reference(x, pos, conv, area, mask)
    assert (conv(x, ei, ew, node_weight=area, mask=mask) - ref).abs().max() < 1e-12
    assert (conv(x, ei, ew, node_weight=area, mask=mask, fast=False) - ref).abs().max() < 1e-12
    for b in range(4):  # [N, C] calls
        assert (conv(x[b], ei, ew, node_weight=area, mask=mask) - ref[b]).abs().max() < 1e-12
    conv.bind(ei, ew, node_weight=area, mask=mask)
    assert (conv(x) - ref).abs().max() < 1e-12
    # hidden points contribute nothing
    x2 = x.clone()
    x2[:, ~mask] = 1e6
    assert (conv(x2) - ref).abs().max() < 1e-12


def test_pyg_batch_of_different_graphs_equals_each_graph_alone():
    from torch_geometric.data import Batch, Data

    conv = SphericalConv(3, 4, 0.5, num_basis=3, basis="gaussian")
    datas = []
    for seed, n in ((0, 120), (1, 200), (2, 90)):
        pos = random_sphere(n, seed)
        ei, ew, area = graph(pos, 0.5)
        m = torch.rand(n, generator=torch.Generator().manual_seed(seed)) > 0.2
        x = torch.randn(n, 3, generator=torch.Generator().manual_seed(10 + seed))
        datas.append(Data(x=x, pos=pos, edge_index=ei, edge_weight=ew, area=area, mask=m))
    b = Batch.from_data_list(datas)
    y = conv(b.x, b.edge_index, b.edge_weight, node_weight=b.area, mask=b.mask)
    for i, d in enumerate(datas):
        ref = dense_reference(d.x, d.pos, conv, d.area, d.mask)
        assert (y[b.batch == i] - ref).abs().max() < 1e-12


def test_never_stale_fresh_masks_and_fresh_graphs():
    # A cache keyed by tensor addresses reused old geometry for a fresh mask or graph that
    # landed at a freed address. Every call here gets new inputs of the same size.
    gen = torch.Generator().manual_seed(0)
    pos = random_sphere(200, 5)
    ei, ew, area = graph(pos, 0.45)
    x = torch.randn(2, 200, 3, generator=gen)
    conv = SphericalConv(3, 4, 0.45, num_basis=3)
    bound = SphericalConv(3, 4, 0.45, num_basis=3)
    bound.load_state_dict(conv.state_dict())
    bound.bind(ei, ew, node_weight=area)
    for _ in range(50):
        mask = torch.rand(200, generator=gen) > 0.5  # fresh tensor, same size
        ref = dense_reference(x, pos, conv, area, mask)
        assert (conv(x, ei, ew, node_weight=area, mask=mask) - ref).abs().max() < 1e-12
        assert (bound(x, mask=mask) - ref).abs().max() < 1e-12
        assert (bound.bind(ei, ew, node_weight=area, mask=mask)(x) - ref).abs().max() < 1e-12
        bound.bind(ei, ew, node_weight=area)
    # fresh point clouds with same-size k-NN graphs (PointConv, euclidean distances)
    pconv = PointConv(3, 2, 1.5, num_basis=3)
    for _ in range(50):
        p = torch.randn(60, 3, generator=gen)
        kei, kew = knn_graph(p, 8)
        xp = torch.randn(60, 3, generator=gen)
        adj = torch.zeros(60, 60, dtype=torch.bool)
        adj[kei[1], kei[0]] = True  # which pairs are edges; distances come from p
        assert (pconv(xp, kei, kew) - _dense_on(xp, p, pconv, adj)).abs().max() < 1e-12


def test_pyg_form_reuses_its_plan_only_for_the_same_graph_by_value():
    """The PyG form keeps the last graph's plan: a loader's batches of one grid share it, a
    new graph or the caller's tensor edited in place gets a new one, with every gradient."""
    gen = torch.Generator().manual_seed(3)
    pos = random_sphere(150, 6, dtype=torch.float64)
    ei, ew, area = graph(pos, 0.5)
    conv = SphericalConv(3, 4, 0.5, num_basis=3).double()
    up_conv = UprightConv(3, 4, 0.5, num_basis=3).double()
    up = _unit(torch.randn(1, 3, generator=gen, dtype=torch.float64))
    perm = torch.randperm(150, generator=gen)
    moved = torch.empty_like(pos)
    moved[perm] = pos  # point k is now numbered perm[k]
    for step in range(3):
        x = torch.randn(150, 3, generator=gen, dtype=torch.float64, requires_grad=True)
        p = moved if step == 2 else pos
        y = conv(x, ei if step != 1 else ei.clone(), ew, node_weight=area[perm.argsort()]
                 if step == 2 else area)
        ref = dense_reference(x, p, conv, area[perm.argsort()] if step == 2 else area)
        g = torch.randn(y.shape, generator=gen, dtype=torch.float64)
        gx, = torch.autograd.grad((y * g).sum(), x)
        gx_ref, = torch.autograd.grad((ref * g).sum(), x)
        assert (y - ref).abs().max() < 1e-12 and (gx - gx_ref).abs().max() < 1e-12
        y_up = up_conv(x, up, ei, ew, pos=p)
        assert (y_up - upright_reference(x[None], up, p, up_conv)[0]).abs().max() < 1e-12
        if step == 0:
            plan = conv._plans["last"]
        elif step == 1:  # the same graph in another tensor: the same plan
            assert conv._plans["last"] is plan
            ei.copy_(perm[ei])  # the caller's tensor, edited in place: the moved points' graph
        else:
            assert conv._plans["last"] is not plan


def _dense_on(x, pos, conv, adj):
    """The dense formula in R3 (hat basis, normalize="mean") over the pairs in ``adj``."""
    K, r = conv.num_basis, conv.radius
    d = (pos[:, None] - pos[None]).norm(dim=-1)
    k = torch.arange(K, dtype=d.dtype)
    phi = torch.relu(1 - ((d / r)[..., None] * K - k).abs()) * ((d < r) & adj)[..., None]
    a = phi / phi.sum((1, 2)).clamp_min(1e-12)[:, None, None]  # normalize="mean"
    W = conv.weight.view(K, conv.in_channels, conv.out_channels)
    return torch.einsum("ijk,jc,kco->io", a, x, W) + conv.bias


def test_gradcheck_of_the_default_path_in_every_input():
    pos = random_sphere(40, 4)
    ei, ew, area = graph(pos, 0.8)
    assert (ew == 0).sum() == 40  # self-loops: d = 0 must have a finite gradient
    mask = torch.rand(40, generator=torch.Generator().manual_seed(1)) > 0.2
    x = torch.randn(2, 40, 2, requires_grad=True)
    w_req, a_req = ew.clone().requires_grad_(True), area.clone().requires_grad_(True)
    for c_out, basis in ((3, "gaussian"), (5, "gaussian"), (3, "mlp")):  # mix / aggregate first
        # the first in full; the others on random projections (gradcheck's fast mode: the
        # full Jacobians took 20 s)
        fast = (c_out, basis) != (3, "gaussian")
        conv = SphericalConv(2, c_out, 0.8, num_basis=3, basis=basis)
        params = dict(conv.named_parameters())
        names = list(params)
        leaves = [p.detach().clone().requires_grad_(True) for p in params.values()]

        def general(x, w, a, *p, conv=conv, names=names):
            return torch.func.functional_call(conv, dict(zip(names, p)), (x, ei, w),
                                              {"node_weight": a, "mask": mask})

        assert torch.autograd.gradcheck(general, (x, w_req, a_req, *leaves), fast_mode=fast)
        assert torch.autograd.gradcheck(general, (x[0], w_req, a_req, *leaves), fast_mode=fast)

        def static(x, w, a, *p, conv=conv, names=names):
            conv.bind(ei, w, node_weight=a, mask=mask)
            return torch.func.functional_call(conv, dict(zip(names, p)), (x,))

        assert torch.autograd.gradcheck(static, (x, w_req, a_req, *leaves), fast_mode=fast)
    # the learnable basis's parameters get gradients through the default path
    conv = SphericalConv(2, 3, 0.8, num_basis=3, basis="mlp").bind(ei, ew, node_weight=area)
    conv(x).square().sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in conv.kernel.parameters())
    mlp = SphericalConv(2, 2, 0.8, kernel="mlp", hidden=4)
    assert torch.autograd.gradcheck(lambda x, w: mlp(x, ei, w, node_weight=area), (x, w_req))
    # bound areas alone asking for a gradient (the distances fixed): no cached coefficients
    conv = SphericalConv(2, 3, 0.8, num_basis=3, basis="gaussian")
    xd = x.detach()
    for _ in range(2):
        assert torch.autograd.gradcheck(
            lambda a: conv.bind(ei, ew, node_weight=a, mask=mask)(xd), (a_req,), fast_mode=True)


def test_bound_geometry_follows_to_reset_and_in_place_edits():
    pos = random_sphere(150, 6)
    ei, ew, area = graph(pos, 0.5)
    conv = SphericalConv(3, 4, 0.5, basis="gaussian").bind(ei, ew, node_weight=area)
    x = torch.randn(2, 150, 3)
    y = conv(x)
    assert conv._coef is not None  # cached while nothing needs its gradient
    conv.reset_parameters()
    assert conv._coef is None
    torch.testing.assert_close(conv(x), dense_reference(x, pos, conv, area), rtol=0, atol=1e-12)
    mask = torch.ones(150, dtype=torch.bool)
    conv.bind(ei, ew, node_weight=area, mask=mask)
    y = conv(x)
    conv.bound_mask[:50] = False  # an in-place edit is seen through the version counter
    torch.testing.assert_close(conv(x), dense_reference(x, pos, conv, area, conv.bound_mask),
                               rtol=0, atol=1e-12)
    assert not torch.allclose(conv(x), y)
    y64 = conv(x)
    conv.float()  # the bound geometry follows .to(): float32 distances, long indices
    assert conv.bound_edge_weight.dtype == torch.float32 and conv.plan.edge_index.dtype == torch.long
    torch.testing.assert_close(conv(x.float()), y64.float(), rtol=1e-4, atol=1e-4)
    conv.double()
    names = {n for n, _ in conv.named_buffers()}
    assert {"bound_edge_index", "bound_edge_weight", "plan.crow0", "plan.col0"} <= names
    assert "bound_edge_index" not in conv.state_dict()  # non-persistent: checkpoints stay small


def test_a_per_call_mask_is_cached_by_value_beside_the_bound_one_with_gradients():
    """A camera's field of view passed on every call (``predict``'s frames) is computed
    once; an equal mask in a new tensor hits the cache, an edited one does not, the bound
    mask keeps its own coefficients, and gradients through the cached ones are right."""
    gen = torch.Generator().manual_seed(3)
    pos = random_sphere(180, 8)
    ei, ew, area = graph(pos, 0.5)
    conv = SphericalConv(3, 4, 0.5, num_basis=3, basis="gaussian").bind(ei, ew, node_weight=area)
    x = torch.randn(2, 180, 3, generator=gen, requires_grad=True)
    fov = torch.rand(180, generator=gen) > 0.4
    whole = conv(x)
    bound = conv._coef
    for m in (fov, fov.clone(), fov.clone()):  # the same field of view, frame after frame
        y = conv(x, mask=m)
        ref = dense_reference(x, pos, conv, area, m)
        assert (y - ref).abs().max() < 1e-12
        g, gr = (torch.autograd.grad(t.square().sum(), x)[0] for t in (y, ref))
        assert (g - gr).abs().max() < 1e-12
    cached = conv._call_coef
    assert conv(x, mask=fov.clone()) is not None and conv._call_coef is cached
    assert conv._coef is bound and (conv(x) - whole).abs().max() == 0  # the bound one kept
    fov[:60] = ~fov[:60]  # the caller edits its mask in place: recomputed
    assert (conv(x, mask=fov) - dense_reference(x, pos, conv, area, fov)).abs().max() < 1e-12
    assert conv._call_coef is not cached
    y32 = conv.float()(x.detach().float(), mask=fov)  # another dtype: its own coefficients
    assert conv._call_coef.dtype == torch.float32
    torch.testing.assert_close(y32, dense_reference(x.detach(), pos, conv.double(), area, fov).float(),
                               rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("wide", [False, True], ids=["blockwise", "wide"])
def test_inference_mode_calls_and_graphs_bound_in_it(monkeypatch, wide):
    """What a call under ``torch.inference_mode()`` keeps serves later training calls
    (values and gradients against the dense reference); a graph bound inside inference
    mode has no version counters, so its in-place edits are followed by recomputing."""
    monkeypatch.setattr(aggregate, "WIDE", wide)
    gen = torch.Generator().manual_seed(4)
    pos = random_sphere(160, 5)
    ei, ew, area = graph(pos, 0.5)
    conv = SphericalConv(3, 4, 0.5, num_basis=3, basis="gaussian").double()
    conv.bind(ei, ew, node_weight=area)
    x = torch.randn(2, 160, 3, generator=gen, dtype=torch.float64)
    fov = torch.rand(160, generator=gen) > 0.4
    with torch.inference_mode():
        for m in (fov, None):
            assert (conv(x, mask=m) - dense_reference(x, pos, conv, area, m)).abs().max() < 1e-12
    xg = x.clone().requires_grad_()
    for m in (fov, None):
        y, ref = conv(xg, mask=m), dense_reference(xg, pos, conv, area, m)
        assert (y - ref).abs().max() < 1e-12
        (g, gw), (gr, gwr) = (torch.autograd.grad(t.square().sum(), (xg, conv.weight))
                              for t in (y, ref))
        assert (g - gr).abs().max() < 1e-10 and (gw - gwr).abs().max() < 1e-10
    with torch.inference_mode():
        inner = SphericalConv(3, 4, 0.5, num_basis=3, basis="gaussian").double()
        inner.bind(ei.clone(), ew.clone(), node_weight=area.clone())
        m = fov.clone()
        for _ in range(2):
            ref = dense_reference(x, pos, inner, inner.bound_node_weight, m)
            assert (inner(x, mask=m) - ref).abs().max() < 1e-12
            inner.bound_node_weight.mul_(torch.linspace(0.5, 2, 160, dtype=torch.float64))
            m[:50] = ~m[:50]


@functools.cache
def _sequence_case():
    pos = random_sphere(150, 11)
    ei, ew, area = graph(pos, 0.5)
    conv = SphericalConv(3, 4, 0.5, num_basis=3, basis="gaussian").double()
    other = SphericalConv(3, 2, 0.5, num_basis=3).double()
    return (pos, conv.bind(ei, ew, node_weight=area), other.bind(ei, ew, node_weight=area), area)


@settings(max_examples=25, deadline=None)
@given(steps=st.lists(st.sampled_from(["same", "copy", "edit", "new", "none", "other layer"]),
                      min_size=3, max_size=12), seed=st.integers(0, 10_000))
def test_any_sequence_of_fields_of_view_gives_the_reference(steps, seed):
    """Whatever sequence of calls a bound layer sees (the same mask again, an equal copy,
    the caller's mask edited in place, a new one, no mask, another layer's call in
    between), every answer is the dense reference's for that call's mask. (Masks keep
    80% of the points, as the other tests': a centre that sees only its kernel's rim
    amplifies rounding past 1e-10, which is not staleness.)"""
    gen = torch.Generator().manual_seed(seed)
    pos, conv, other, area = _sequence_case()  # shared: the caches carry over between examples
    x = torch.randn(1, len(pos), 3, generator=gen, dtype=pos.dtype)
    mask = torch.rand(len(pos), generator=gen) > 0.2
    with torch.no_grad():
        for step in steps:
            if step == "edit":
                mask[torch.randint(0, len(pos), (20,), generator=gen)] ^= True
            elif step == "new":
                mask = torch.rand(len(pos), generator=gen) > 0.2
            elif step == "other layer":
                other(x, mask=torch.rand(len(pos), generator=gen) > 0.2)
            m = None if step == "none" else mask.clone() if step == "copy" else mask
            y = conv(x, mask=m)
            assert (y - dense_reference(x, pos, conv, area, m)).abs().max() < 1e-10


def test_a_call_interrupted_by_another_cameras_call_keeps_its_own_field_of_view(monkeypatch):
    """One model serving two cameras from two threads: another thread's call with another
    field of view can run between this call's cache check and its return. Replayed here
    in one thread, at that exact point (inside the mask comparison): the interrupted call
    still answers with its own mask's coefficients."""
    from usf_graph.nn import conv as conv_module

    pos = random_sphere(160, 9)
    ei, ew, area = graph(pos, 0.5)
    gen = torch.Generator().manual_seed(8)
    x = torch.randn(1, 160, 3, generator=gen, dtype=pos.dtype)
    up = _unit(torch.randn(1, 3, generator=gen, dtype=pos.dtype))
    mine, other = (torch.rand(160, generator=gen) > 0.5 for _ in range(2))
    same = conv_module._same
    plain = SphericalConv(3, 4, 0.5, num_basis=3).double().bind(ei, ew, node_weight=area)
    oriented = UprightConv(3, 4, 0.5, num_basis=3).double().bind(ei, ew, node_weight=area, pos=pos)
    for layer, args in ((plain, (x,)), (oriented, (x, up))):
        with torch.no_grad():
            want = layer(*args, mask=mine)  # cached now: the next call with it is a hit
            interrupted = []

            def other_thread_runs_here(cached, mask, layer=layer, args=args, interrupted=interrupted):
                result = same(cached, mask)
                if not interrupted:
                    interrupted.append(True)
                    layer(*args, mask=other)  # the other camera's whole call
                return result

            monkeypatch.setattr(conv_module, "_same", other_thread_runs_here)
            got = layer(*args, mask=mine.clone())
            monkeypatch.setattr(conv_module, "_same", same)
        assert interrupted and (got - want).abs().max() == 0


def test_layers_with_kept_geometry_copy_and_pickle():
    """After calls that fill every cache (per-call mask, tiles, oriented basis), a layer
    still deep-copies and pickles (sparse tensors and weak references are not kept in
    the copy) and the copy gives the same answer."""
    import copy
    import pickle

    pos = random_sphere(180, 8)
    ei, ew, area = graph(pos, 0.5)
    gen = torch.Generator().manual_seed(7)
    x = torch.randn(2, 180, 3, generator=gen, dtype=pos.dtype)
    up = _unit(torch.randn(2, 3, generator=gen, dtype=pos.dtype))
    m = torch.rand(180, generator=gen) > 0.3
    for conv, args in ((SphericalConv(3, 4, 0.5, num_basis=3).bind(ei, ew, node_weight=area), (x,)),
                       (UprightConv(3, 4, 0.5, num_basis=3).double()
                        .bind(ei, ew, node_weight=area, pos=pos), (x, up))):
        conv = conv.double()
        with torch.no_grad():
            y = conv(*args, mask=m)
            for clone in (copy.deepcopy(conv), pickle.loads(pickle.dumps(conv))):
                assert (clone(*args, mask=m) - y).abs().max() == 0
                assert (clone(*args, mask=~m) - conv(*args, mask=~m)).abs().max() == 0


def test_documented_call_and_the_initialization_claim():
    pos = random_sphere(300, 7)
    ei, ew, area = graph(pos, 0.35)
    conv = SphericalConv(5, 6, 0.35, num_basis=4)
    x = torch.randn(300, 5, generator=torch.Generator().manual_seed(0))
    y = conv(x, ei, ew)  # the documented call: no node_weight -> equal weights
    mean = SphericalConv(5, 6, 0.35, num_basis=4, normalize="mean")
    mean.load_state_dict(conv.state_dict())
    torch.testing.assert_close(y, mean(x, ei, ew), rtol=0, atol=1e-14)
    torch.testing.assert_close(y, dense_reference(x, pos, conv), rtol=0, atol=1e-12)
    # the claim: E_W[mean y^2] = mean over (k, c) of E[u_kc^2] (bias 0), for any input
    U = torch.einsum("ijk,jc->ikc", _aggregation(pos, conv, area), x)  # [N, K, C_in]
    target = float(U.square().mean())
    torch.manual_seed(0)
    draws = []
    with torch.no_grad():
        for _ in range(400):
            conv.reset_parameters()
            draws.append(float(conv(x, ei, ew, node_weight=area).square().mean()))
    draws = torch.tensor(draws)
    assert abs(draws.mean() - target) < 4 * draws.std() / math.sqrt(len(draws))
    assert abs(float(draws.mean()) / target - 1) < 0.1


def _aggregation(pos, conv, area):
    """The normalized aggregation weights a_ijk, from the dense reference with W = I."""
    K, C = conv.num_basis, 1
    probe = SphericalConv(C, K, conv.radius, num_basis=K, basis=conv.kernel.basis, bias=False)
    with torch.no_grad():
        probe.weight.copy_(torch.eye(K).reshape(K * C, K))  # output k = basis k
    eye = torch.eye(len(pos))[..., None]  # x = one-hot per point j
    return dense_reference(eye, pos, probe, area).detach().permute(1, 0, 2)  # [i, j, k]


def test_equivariance_through_the_harness_on_grid_symmetries():
    g = grids.healpix(8)
    R = rotation_from_axis_angle(torch.tensor([0.0, 0, 1]), torch.tensor(math.pi / 2))
    r = 1.7 * g.spacing
    ei, ew = geodesic_radius_graph(g.pos, r)
    mask = g.pos[:, 0] > -0.3
    x = torch.randn(2, len(g), 3, generator=torch.Generator().manual_seed(0))
    for basis in ("hat", "gaussian", "bessel", "mlp"):
        conv = SphericalConv(3, 4, r, num_basis=4, basis=basis)
        err = assert_equivariant(lambda x, m, c=conv: c(x, ei, ew, node_weight=g.area, mask=m),
                                 (x, mask), g.pos, R)
        assert err < 1e-10
        conv.bind(ei, ew, node_weight=g.area)
        assert_equivariant(lambda x, m, c=conv: c(x, mask=m), (x, mask), g.pos, R)
        c32 = conv.float()
        err32 = assert_equivariant(lambda x, m, c=c32: c(x, mask=m), (x.float(), mask), g.pos, R)
        assert err32 < 1e-5
    with pytest.raises(AssertionError, match="not equivariant"):  # the harness can fail
        assert_equivariant(lambda x: x * g.pos[:, :1], x, g.pos, R)


@pytest.mark.parametrize("kernel, basis", [("basis", "hat"), ("basis", "gaussian"),
                                           ("basis", "bessel"), ("mlp", "hat")])
def test_exact_so3_equivariance_on_moving_point_sets(kernel, basis):
    pos = random_sphere(400, 0)
    x = torch.randn(400, 3, generator=torch.Generator().manual_seed(1))
    conv = SphericalConv(3, 5, radius=0.35, num_basis=4, kernel=kernel, basis=basis)

    def run(p, x):
        ei, ew = geodesic_radius_graph(p, 0.35)  # rebuilt from the moved points
        return conv(x, ei, ew, node_weight=torch.as_tensor(voronoi_areas(p.numpy())))

    for seed in range(3):
        assert assert_motion_invariant(run, pos, (x,), rotation=_rot(seed)) < 1e-10


def _rot(seed):
    from usf_graph.geometry import random_rotation

    return random_rotation(seed=10 + seed)


def test_tiled_plan_matches_the_reference_with_every_gradient():
    g = grids.healpix(8)  # HEALPix nested numbering is a Z-order curve: narrow halos
    r = 1.6 * g.spacing
    ei, ew = geodesic_radius_graph(g.pos, r)
    plan = EdgePlan(ei, len(g), tile_rows=64)
    assert len(plan.bounds) == 12 and sum(len(getattr(plan, f"cols{t}")) for t in range(12)) < 2 * len(g)
    shuffled = torch.randperm(len(g), generator=torch.Generator().manual_seed(0))
    assert len(EdgePlan(shuffled[ei], len(g), tile_rows=64).bounds) == 1  # no locality
    x = torch.randn(2, len(g), 3, generator=torch.Generator().manual_seed(1), requires_grad=True)
    mask = torch.rand(len(g), generator=torch.Generator().manual_seed(2)) > 0.2
    for c_out in (2, 7):  # mixing first and aggregating first
        conv = SphericalConv(3, c_out, r, num_basis=3, basis="gaussian")
        w = ew.clone().requires_grad_(True)
        conv.bind(ei, w, node_weight=g.area, mask=mask, plan=plan)
        fast = conv(x)
        ref = conv(x, ei, w, node_weight=g.area, mask=mask, fast=False)
        assert (fast - ref).abs().max() < 1e-12
        go = torch.randn_like(fast)
        g_fast = torch.autograd.grad(fast, (x, conv.weight, w), go)
        g_ref = torch.autograd.grad(ref, (x, conv.weight, w), go)
        for a, b in zip(g_fast, g_ref):
            assert (a - b).abs().max() < 1e-11
    with pytest.raises(ValueError, match="another graph"):
        conv.bind(ei[:, 1:], ew[1:], plan=plan)


def test_pyg_conventions_sequential_repr_reset_compile():
    conv = SphericalConv(3, 8, 0.2, num_basis=4)
    assert repr(conv) == ("SphericalConv(3, 8, radius=0.2, num_basis=4, basis='hat', "
                          "normalize='area')")
    w0 = conv.weight.detach().clone()
    conv.reset_parameters()
    assert not torch.equal(w0, conv.weight)
    g = grids.icosahedral(2)
    ei, ew = geodesic_radius_graph(g.pos, 0.5)
    assert "bound=162 nodes" in repr(SphericalConv(3, 4, 0.5).bind(ei, ew, g.area))
    model = Sequential("x, ei, ew, a", [(SphericalConv(3, 4, 0.5), "x, ei, ew, a -> x"),
                                        torch.nn.ReLU(),
                                        (SphericalConv(4, 2, 0.5), "x, ei, ew, a -> x")])
    x = torch.randn(2, len(g), 3)
    y = model(x, ei, ew, g.area)
    assert y.shape == (2, len(g), 2)
    compiled = torch.compile(model, backend="eager")
    torch.testing.assert_close(compiled(x, ei, ew, g.area), y)


def _masked_pairs(ei, m, n):
    """The edge mask ``m [E]`` as a dense ``[N_i, N_j]`` matrix (1 off the graph)."""
    M = torch.ones(n, n, dtype=m.dtype)
    M[ei[1], ei[0]] = m
    return M


@pytest.mark.parametrize("normalize", ["area", "mean", None])
def test_explain_mode_scales_each_message_by_its_edge_mask_on_every_path(normalize):
    """PyG's explainers scale messages by an edge mask; the sparse fast path has no messages,
    so explain mode must take the per-edge one: against the dense formula with each pair's
    coefficients times its mask, PyG form and bound, with the mask's gradient."""
    from torch_geometric.explain.algorithm.utils import clear_masks, set_masks

    pos = random_sphere(80, 5)
    ei, ew, area = graph(pos, 0.6)
    keep = torch.rand(80, generator=torch.Generator().manual_seed(1)) > 0.2
    x = torch.randn(3, 80, 4, generator=torch.Generator().manual_seed(2))
    conv = SphericalConv(4, 5, 0.6, num_basis=3, normalize=normalize)
    m = torch.rand(ei.shape[1], generator=torch.Generator().manual_seed(3)).requires_grad_()
    a = dense_coefficients(pos, conv, area, keep) * _masked_pairs(ei, m, 80)[..., None]
    W = conv.weight.view(3, 4, 5)
    ref = torch.einsum("ijk,...jc,kco->...io", a, x, W) + conv.bias
    (g_ref,) = torch.autograd.grad(ref.square().sum(), m)
    set_masks(conv, m, ei, apply_sigmoid=False)
    y = conv(x, ei, ew, node_weight=area, mask=keep)
    torch.testing.assert_close(y, ref, atol=1e-12, rtol=0)
    (g,) = torch.autograd.grad(y.square().sum(), m)
    torch.testing.assert_close(g, g_ref, atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(conv(x[1], ei, ew, node_weight=area, mask=keep), ref[1],
                               atol=1e-12, rtol=0)
    conv.bind(ei, ew, node_weight=area, mask=keep)
    torch.testing.assert_close(conv(x), ref, atol=1e-12, rtol=0)
    clear_masks(conv)  # and back to the plain layer
    torch.testing.assert_close(conv(x), dense_reference(x, pos, conv, area, keep),
                               atol=1e-12, rtol=0)
    set_masks(conv, m[:-1], ei[:, :-1], apply_sigmoid=False)
    with pytest.raises(ValueError, match="edge mask has .* entries"):
        conv(x)
    clear_masks(conv)
    conv.explain = True  # explain mode, but no explainer has set a mask
    with pytest.raises(ValueError, match="explain mode without an edge mask: let an Explainer"):
        conv(x)


def test_pyg_message_hooks_see_the_messages_that_make_the_output():
    """A hook on ``message`` (PyG's ``register_message_forward_hook``) is called on the bound
    fast path too, and what it sees, summed into each centre and weighted, is the output."""
    pos = random_sphere(60, 6)
    ei, ew, area = graph(pos, 0.7)
    x = torch.randn(2, 60, 3, generator=torch.Generator().manual_seed(4))
    conv = SphericalConv(3, 4, 0.7, num_basis=3).bind(ei, ew, node_weight=area)
    seen = []
    handle = conv.register_message_forward_hook(lambda m, inputs, out: seen.append(out))
    y = conv(x)
    handle.remove()
    (msg,) = seen  # [E, K, B, C]
    agg = torch.zeros(60, *msg.shape[1:]).index_add_(0, ei[1], msg)
    W = conv.weight.view(3, 3, 4)
    torch.testing.assert_close(torch.einsum("nkbc,kco->bno", agg, W) + conv.bias, y,
                               atol=1e-12, rtol=0)
    torch.testing.assert_close(y, dense_reference(x, pos, conv, area), atol=1e-12, rtol=0)
    conv(x)
    assert len(seen) == 1  # removed: the fast path again
    upright = UprightConv(3, 4, 0.7).bind(ei, ew, node_weight=area, pos=pos)
    upright.register_message_forward_hook(lambda m, inputs, out: None)
    with pytest.raises(ValueError, match="hooks are never called on it"):
        upright(x, _unit(torch.randn(2, 3)))


def test_gnn_explainer_finds_exactly_the_receptive_field():
    """``torch_geometric.explain.Explainer`` with ``GNNExplainer`` on two layers: the edges
    it can credit for a point's output are those into the point and into its neighbours."""
    from torch_geometric.explain import Explainer, GNNExplainer

    g = grids.icosahedral(2)
    ei, ew = geodesic_radius_graph(g.pos, 0.35)
    c1, c2 = SphericalConv(3, 6, 0.35), SphericalConv(6, 2, 0.35)

    class Net(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.c1, self.c2 = c1, c2

        def forward(self, x, edge_index, edge_weight):
            return self.c2(self.c1(x, edge_index, edge_weight).tanh(), edge_index, edge_weight)

    explainer = Explainer(Net(), GNNExplainer(epochs=3), explanation_type="model",
                          edge_mask_type="object", node_mask_type=None,
                          model_config=dict(mode="multiclass_classification", task_level="node",
                                            return_type="raw"))
    x = torch.randn(len(g), 3, generator=torch.Generator().manual_seed(0))
    e = explainer(x, ei, edge_weight=ew, index=7)
    near = torch.zeros(len(g), dtype=torch.bool)
    near[ei[0, ei[1] == 7]] = True  # point 7 and its neighbours (self-loops included)
    assert torch.equal(e.edge_mask > 0, near[ei[1]])


def test_torch_func_transforms_and_forward_mode_through_both_layers():
    """``torch.func`` (per-sample gradients as ``vmap(grad)``, ``jacrev``, ``jvp``) and
    forward-mode AD, which the sparse kernel's hand-written backward cannot serve: they
    take the plain form and give what ordinary autograd and the layer's linearity give."""
    import torch.autograd.forward_ad as fwAD
    from torch.func import functional_call, grad, jacrev, jvp, vmap

    g = grids.icosahedral(1)
    ei, ew = geodesic_radius_graph(g.pos, 0.7)
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(4, len(g), 3, generator=gen)
    up = _unit(torch.randn(4, 3, generator=gen))
    for conv, extra in ((SphericalConv(3, 2, 0.7).bind(ei, ew, node_weight=g.area), ()),
                        (UprightConv(3, 2, 0.7).bind(ei, ew, node_weight=g.area, pos=g.pos), (up,))):
        params = {k: v.detach() for k, v in conv.named_parameters()}

        def loss(p, xb, *u, conv=conv):
            return functional_call(conv, p, (xb[None], *(t[None] for t in u))).square().sum()

        per = vmap(grad(loss), in_dims=(None, 0) + (0,) * len(extra))(params, x, *extra)
        for b in range(4):
            y = conv(x[b:b + 1], *(t[b:b + 1] for t in extra)).square().sum()
            torch.testing.assert_close(per["weight"][b], torch.autograd.grad(y, conv.weight)[0],
                                       atol=1e-12, rtol=1e-12)
        lin = lambda t, conv=conv, extra=extra: conv(t, *(e[:len(t)] for e in extra)) - conv.bias  # noqa: E731
        v = torch.randn(x.shape, generator=gen)
        torch.testing.assert_close(jvp(lin, (x,), (v,))[1], lin(v), atol=1e-12, rtol=0)
        with fwAD.dual_level():
            tangent = fwAD.unpack_dual(lin(fwAD.make_dual(x, v))).tangent
        torch.testing.assert_close(tangent, lin(v), atol=1e-12, rtol=0)
        J = jacrev(lin)(x[:1])  # [1, N, 2, 1, N, 3]: the operator itself
        torch.testing.assert_close(torch.einsum("aibcjd,cjd->aib", J, v[:1]), lin(v[:1]),
                                   atol=1e-12, rtol=0)
    pyg = SphericalConv(3, 2, 0.7)  # PyG's form: the plan it keeps is built under grad

    def total(t, fast=True):
        return pyg(t, ei, ew, node_weight=g.area, fast=fast).sum()

    torch.testing.assert_close(grad(total)(x), grad(functools.partial(total, fast=False))(x),
                               atol=1e-12, rtol=0)
    for t in pyg._plans["last"].buffers():  # plain tensors, not the transform's wrappers
        t.untyped_storage()


def test_bad_inputs_name_the_problem():
    with pytest.raises(ValueError, match="normalize"):
        SphericalConv(1, 1, 0.1, normalize="sum")
    with pytest.raises(ValueError, match="kernel must be 'basis' or 'mlp', got 'gauss'"):
        SphericalConv(1, 1, 0.1, kernel="gauss")
    for args, said in (((0, 4, 0.3), "in_channels must be a positive integer, got 0"),
                       ((3, 2.5, 0.3), "out_channels must be a positive integer, got 2.5"),
                       ((3, 4, 0.0), "radius must be a positive finite geodesic distance"),
                       ((3, 4, float("nan")), "radius must be .* got nan")):
        with pytest.raises(ValueError, match=said):
            SphericalConv(*args)
    conv = SphericalConv(2, 2, 0.5)
    g = grids.icosahedral(1)
    ei, ew = geodesic_radius_graph(g.pos, 0.5)
    n = len(g)
    cases = [
        (lambda: conv(torch.randn(n, 3), ei, ew), "x must be"),
        (lambda: conv(torch.randn(n, 2)), "no graph"),
        (lambda: conv(torch.randn(n, 2), ei, None), "edge_weight"),
        (lambda: conv(torch.randn(n, 2), ei, ew, node_weight=torch.ones(n + 1)), r"\[42\]"),
        (lambda: conv(torch.randn(n - 2, 2), ei, ew), "outside"),
        (lambda: conv(torch.randn(n, 2), ei, ew * float("nan")), "NaN"),
        (lambda: conv(torch.randn(n, 2), ei, ew, node_weight=-torch.ones(n)), "areas: finite and >= 0"),
        (lambda: conv.bind(ei, ew, node_weight=torch.full((n,), float("inf"))), "areas"),
        (lambda: conv.bind(ei, ew)(torch.randn(2, n + 5, 2)), f"{n + 5} points, the bound graph has {n}"),
        (lambda: conv.bind(ei, ew)(torch.randn(n, 2), ei[:, :0]), "edge_weight"),
        (lambda: conv(torch.randn(n, 2), ei[:, :-1], ew),
         rf"need edge_index \[2, E\] and edge_weight \[E\], got \(2, {ei.shape[1] - 1}\)"),
        (lambda: conv.bind(ei, ew)(torch.randn(n, 2), edge_weight=ew),
         "edge_weight/node_weight without edge_index"),
        (lambda: conv.bind(ei, ew)(torch.randn(n, 2), mask=torch.ones(n - 1, dtype=torch.bool)),
         rf"mask must have shape \[{n}\], got \({n - 1},\)"),
    ]
    for f, match in cases:
        with pytest.raises(ValueError, match=match):
            f()


def upright_reference(x, up, pos, conv, node_weight=None, mask=None, pairs=None):
    """UprightConv's formula, dense: the direction from p_i to p_j written as
    ``(p_i x p_j) x p_i``, normalized (0 for i = j), read along and across up, less its
    mean over what each basis sees; ``pairs [N_i, N_j]`` scales each pair's term (an
    explainer's edge mask; the means stay the layer's)."""
    a0 = dense_coefficients(pos, conv, node_weight, mask)
    a = a0 if pairs is None else a0 * pairs[..., None]
    n = pos[:, None].expand(-1, len(pos), -1)
    u = torch.linalg.cross(torch.linalg.cross(n, pos[None].expand_as(n), dim=-1), n, dim=-1)
    u = u / u.norm(dim=-1, keepdim=True) * ~torch.eye(len(pos), dtype=torch.bool)[..., None]
    u = u.nan_to_num(0.0)  # i = j: no direction
    W = conv.weight.view(3, conv.num_basis, conv.in_channels, conv.out_channels)
    y = torch.einsum("ijk,bjc,kco->bio", a, x, W[0])
    for part, v in ((1, u), (2, torch.linalg.cross(n, u, dim=-1))):
        s = torch.einsum("ijc,bc->bij", v, up)
        centred = s[..., None] - (a0 * s[..., None]).sum(2, keepdim=True) / \
            a0.sum(1).clamp_min(1e-12)[None, :, None]  # a centre that sees nothing: 0
        y = y + torch.einsum("ijk,bijk,bjc,kco->bio", a, centred, x, W[part])
    return y + conv.bias


def _unit(v):
    return v / v.norm(dim=-1, keepdim=True)


def test_upright_conv_equals_its_dense_reference_with_gradients_on_fresh_masks():
    pos = random_sphere(250, 5, dtype=torch.float64)
    ei, ew, area = graph(pos, 0.45)
    gen = torch.Generator().manual_seed(7)
    conv = UprightConv(4, 5, 0.45, num_basis=3, basis="gaussian").double()
    with torch.no_grad():  # a bias of zeros (its initialization) would pass unadded
        conv.bias.normal_(generator=gen)
    mask = torch.rand(250, generator=gen) > 0.3
    conv.bind(ei, ew, node_weight=area, mask=mask, pos=pos)
    for call, m in enumerate([None, torch.rand(250, generator=gen) > 0.5, None]):
        x = torch.randn(3, 250, 4, generator=gen, dtype=torch.float64, requires_grad=True)
        up = _unit(torch.randn(3, 3, generator=gen, dtype=torch.float64)).requires_grad_()
        y = conv(x, up, mask=m)
        ref = upright_reference(x, up, pos, conv, area, mask if m is None else m)
        assert (y - ref).abs().max() < 1e-12, call
        one = conv(x[1], up[1:2], ei, ew, area, mask if m is None else m, pos=pos)  # PyG's form
        assert (one - ref[1]).abs().max() < 1e-12, call
        g = torch.randn(y.shape, generator=gen, dtype=torch.float64)
        got = torch.autograd.grad(y, (x, up, conv.weight), g)
        want = torch.autograd.grad(ref, (x, up, conv.weight), g)
        for a, b in zip(got, want):
            assert (a - b).abs().max() < 1e-10 * (1 + b.abs().max()), call
    # the kernel does see the direction of up: turning up alone changes the output
    up = _unit(torch.randn(3, 3, generator=gen, dtype=torch.float64))
    assert (conv(x, up) - conv(x, -up)).abs().max() > 1e-2
    # ... but not a constant signal, even where the mask cuts a neighbourhood
    one = torch.ones(3, 250, 4, dtype=torch.float64)
    iso = UprightConv(4, 5, 0.45, num_basis=3, basis="gaussian").double()
    with torch.no_grad():
        iso.weight.copy_(conv.weight)
        iso.bias.copy_(conv.bias)
        iso.weight.view(3, -1, 5)[1:] = 0  # the isotropic part alone
    iso.bind(ei, ew, node_weight=area, mask=mask, pos=pos)
    assert (conv(one, up) - iso(one, up)).abs().max() < 1e-12


def test_upright_conv_in_explain_mode_scales_each_message_by_its_edge_mask():
    """PyG's explain mode on UprightConv: each pair's term times its edge's mask (through
    a sigmoid, as ``GNNExplainer`` sets it), both forms, with the mask's gradient."""
    from torch_geometric.explain.algorithm.utils import clear_masks, set_masks

    pos = random_sphere(70, 8, dtype=torch.float64)
    ei, ew, area = graph(pos, 0.6)
    gen = torch.Generator().manual_seed(9)
    conv = UprightConv(3, 4, 0.6, num_basis=2).double()
    keep = torch.rand(70, generator=gen) > 0.25
    x = torch.randn(2, 70, 3, generator=gen, dtype=torch.float64)
    up = _unit(torch.randn(2, 3, generator=gen, dtype=torch.float64))
    logits = torch.randn(ei.shape[1], generator=gen, dtype=torch.float64).requires_grad_()
    ref = upright_reference(x, up, pos, conv, area, keep, _masked_pairs(ei, logits.sigmoid(), 70))
    (g_ref,) = torch.autograd.grad(ref.square().sum(), logits)
    set_masks(conv, logits, ei, apply_sigmoid=True)
    conv.bind(ei, ew, node_weight=area, mask=keep, pos=pos)
    y = conv(x, up)
    torch.testing.assert_close(y, ref, atol=1e-12, rtol=0)
    (g,) = torch.autograd.grad(y.square().sum(), logits)
    torch.testing.assert_close(g, g_ref, atol=1e-10, rtol=1e-10)
    one = conv(x[1], up[1:], ei, ew, area, keep, pos=pos)  # PyG's form
    torch.testing.assert_close(one, ref[1], atol=1e-12, rtol=0)
    clear_masks(conv)
    torch.testing.assert_close(conv(x, up), upright_reference(x, up, pos, conv, area, keep),
                               atol=1e-12, rtol=0)


def test_upright_conv_follows_in_place_edits_of_its_bound_mask_and_weights():
    """The oriented basis kept between calls is rebuilt when the bound mask changes in
    place, and never holds an autograd graph (a learnable basis gets a fresh one)."""
    pos = random_sphere(200, 3, dtype=torch.float64)
    ei, ew, area = graph(pos, 0.5)
    gen = torch.Generator().manual_seed(5)
    x = torch.randn(2, 200, 2, generator=gen, dtype=torch.float64)
    up = _unit(torch.randn(2, 3, generator=gen, dtype=torch.float64))
    mask = torch.ones(200, dtype=torch.bool)
    conv = UprightConv(2, 3, 0.5, num_basis=3, basis="gaussian").double()
    conv.bind(ei, ew, node_weight=area, mask=mask, pos=pos)
    with torch.no_grad():
        before = conv(x, up)
        assert (conv(x, up) - before).abs().max() == 0  # the kept basis: the same answer
        mask[:80] = False
        after = conv(x, up)
    assert (after - upright_reference(x, up, pos, conv, area, mask)).abs().max() < 1e-12
    assert (after - before).abs().max() > 1e-3
    learn = UprightConv(2, 3, 0.5, num_basis=3, basis="mlp").double()
    learn.bind(ei, ew, node_weight=area, mask=mask, pos=pos)
    learn(x, up).sum().backward()
    assert learn._oriented == {} and learn.kernel.mlp[0].weight.grad.abs().sum() > 0
    other = torch.rand(200, generator=gen) > 0.4
    with torch.no_grad():  # a per-call mask keeps its own basis beside the bound mask's
        kept = conv._oriented["bound"]
        cut = conv(x, up, mask=other)
        assert conv._oriented["bound"] is kept and (conv(x, up) - after).abs().max() == 0
        assert (cut - upright_reference(x, up, pos, conv, area, other)).abs().max() < 1e-12
        call = conv._oriented["call"]
        assert (conv(x, up, mask=other.clone()) - cut).abs().max() == 0  # equal by value: kept
        assert conv._oriented["call"] is call
        other[:50] = ~other[:50]  # the caller's mask edited in place: noticed
        edited = conv(x, up, mask=other)
    assert conv._oriented["call"] is not call
    assert (edited - upright_reference(x, up, pos, conv, area, other)).abs().max() < 1e-12


def test_upright_conv_is_exactly_equivariant_when_up_turns_with_the_input():
    g = grids.icosahedral(3)
    axis = g.pos[0].double() / g.pos[0].double().norm()  # a vertex: a 5-fold symmetry axis
    R = rotation_from_axis_angle(axis, torch.tensor(2 * math.pi / 5, dtype=torch.float64))
    sigma = symmetry_permutation(g.pos, R)
    pos = g.pos.double()
    ei, ew = geodesic_radius_graph(pos, 3 * g.spacing)
    conv = UprightConv(3, 4, 3 * g.spacing, num_basis=3, basis="gaussian").double()
    conv.bind(ei, ew, node_weight=g.area.double(), pos=pos)
    gen = torch.Generator().manual_seed(2)
    x = torch.randn(2, len(g), 3, generator=gen, dtype=torch.float64)
    up = _unit(torch.randn(2, 3, generator=gen, dtype=torch.float64))
    mask = g.pos[:, 0] > -0.2
    xr = torch.empty_like(x)
    xr[:, sigma] = x
    for m in (None, mask):
        mr = None if m is None else torch.empty_like(m).index_copy_(0, sigma, m)
        y, yr = conv(x, up, mask=m), conv(xr, up @ R.T, mask=mr)
        assert (yr[:, sigma] - y).abs().max() < 1e-10  # the grid's points are float32
    # the test bites: the same input with up left behind is not the rotated output
    assert (conv(xr, up)[:, sigma] - conv(x, up)).abs().max() > 1e-3


def test_upright_conv_on_a_pyg_batch_of_different_graphs_equals_each_graph_bound():
    from torch_geometric.data import Batch, Data

    gen = torch.Generator().manual_seed(4)
    conv = UprightConv(3, 4, 0.5, num_basis=3).double()
    parts, want = [], []
    for seed, n in ((1, 120), (2, 90)):
        pos = random_sphere(n, seed, dtype=torch.float64)
        ei, ew, area = graph(pos, 0.5)
        mask = torch.rand(n, generator=gen) > 0.2
        x = torch.randn(n, 3, generator=gen, dtype=torch.float64)
        up = _unit(torch.randn(1, 3, generator=gen, dtype=torch.float64))
        parts.append(Data(x=x, pos=pos, edge_index=ei, edge_attr=ew, area=area, mask=mask, up=up))
        conv.bind(ei, ew, node_weight=area, mask=mask, pos=pos)
        want.append(conv(x[None], up)[0])
    b = Batch.from_data_list(parts)
    got = conv(b.x, b.up, b.edge_index, b.edge_attr, node_weight=b.area, mask=b.mask, pos=b.pos,
               batch=b.batch)
    assert (got - torch.cat(want)).abs().max() < 1e-12


def test_upright_conv_errors_name_the_problem():
    pos = random_sphere(50, 1)
    ei, ew, area = graph(pos, 0.6)
    conv = UprightConv(2, 3, 0.6)
    with pytest.raises(ValueError, match="needs pos"):
        conv.bind(ei, ew, node_weight=area)
    with pytest.raises(ValueError, match="needs a graph"):
        conv(torch.randn(1, 50, 2), torch.tensor([[0.0, 0, 1]]))
    with pytest.raises(ValueError, match="pos must be"):
        conv(torch.randn(50, 2), torch.tensor([[0.0, 0, 1]]), ei, ew)
    with pytest.raises(ValueError, match=r"x must be \[N, 2\] with edge_index, got \(1, 50, 2\)"):
        conv(torch.randn(1, 50, 2), torch.tensor([[0.0, 0, 1]]), ei, ew, pos=pos)
    for up in (None, torch.tensor([[0.0, 0, 1], [0.0, 0, 1]])):  # one graph, one up
        with pytest.raises(ValueError, match=r"up must be \[1, 3\] \(one unit up per graph\)"):
            conv(torch.randn(50, 2), up, ei, ew, pos=pos)
    conv.bind(ei, ew, node_weight=area, pos=pos.float())
    with pytest.raises(ValueError, match="up must be"):
        conv(torch.randn(2, 50, 2), torch.tensor([[0.0, 0, 1]]))
    with pytest.raises(ValueError, match=r"x must be \[B, 50, 2\]"):
        conv(torch.randn(50, 2), torch.tensor([[0.0, 0, 1]]))
    assert "UprightConv(2, 3" in repr(conv)


@pytest.mark.parametrize("basis", ["hat", "gaussian", "bessel"])
def test_a_centre_seeing_only_the_kernels_rim_keeps_bounded_coefficients(basis):
    """A hidden point whose only visible neighbour lies just inside the radius (a mask's
    border, float32 geometry): its normalized coefficients stay within the kernel's range
    instead of dividing by a rounded-negative sum (they reached 2e3, then 1e19 one layer on)."""
    r, M = 0.3, 20_000
    d = torch.linspace(0.99 * r, r, M)  # float32 distances at the rim
    ei = torch.stack([torch.arange(M, 2 * M), torch.arange(M)])  # neighbour M + m -> centre m
    mask = torch.arange(2 * M) >= M  # the centres hidden, the neighbours visible
    conv = SphericalConv(2, 3, r, num_basis=3, basis=basis)
    coef = conv._edge_coefficients(ei, d, 2 * M, None, mask)
    assert torch.isfinite(coef).all()
    if basis == "bessel":  # signed bases: bounded by the sinc's range over the envelope
        assert coef.abs().max() < 10
    else:
        assert coef.min() >= 0 and coef.sum(1).max() <= 1 + 1e-5
    x = torch.randn(2 * M, 2, generator=torch.Generator().manual_seed(0))
    y = conv(x, ei, d, mask=mask)
    assert (y - conv.bias).abs().max() < 10 * x.abs().max() * conv.weight.abs().sum(0).max()


def test_an_export_after_a_call_with_another_field_of_view_keeps_its_own():
    """While exporting, a layer reuses the coefficients its last eager call kept only when
    that call's field of view is the exported one: an eager call with another mask
    between the recording and the export must not leave its coefficients in the file."""
    from usf_graph import tracing

    g = grids.icosahedral(2)
    ei, ew = geodesic_radius_graph(g.pos, 0.5)
    conv = SphericalConv(3, 4, 0.5, num_basis=3).bind(ei, ew, node_weight=g.area)

    class Net(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.conv = conv

        def forward(self, x, mask):
            return self.conv(x, mask=mask)

    x = torch.randn(2, len(g), 3, generator=torch.Generator().manual_seed(0))
    field, other = g.pos[:, 0] > -0.2, g.pos[:, 2] > 0.1
    with tracing.fixed_fields() as record:
        want = Net()(x, field)
    Net()(x, other)  # kept now: the other field's coefficients
    with tracing.fixed_fields(record):
        program = torch.export.export(Net(), (x, field))
    torch.testing.assert_close(program.module()(x, field), want, rtol=0, atol=1e-12)
    torch.testing.assert_close(want, dense_reference(x, g.pos, conv, g.area, field),
                               rtol=0, atol=1e-12)
