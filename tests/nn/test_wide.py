"""The one-product form of the sparse kernel (the GPU's) against a per-edge reference and
the blockwise form, with every gradient, on graphs, masks and batch sizes that change
between calls; and the layers' own reference tests run again through it."""

import pytest
import torch

from tests.helpers import random_sphere
from tests.nn import test_conv
from usf_graph.nn import EdgePlan, SphericalConv, aggregate, geodesic_radius_graph
from usf_graph.nn.wide import wide_aggregate


def per_edge(x, weight, coef, edge_index):
    """``y_b[i] = sum_k sum_(j->i) coef_b[e, k] x_b[j] W_k``, edge by edge with index_add:
    shares nothing with either sparse form."""
    j, i = edge_index
    c = coef if coef.dim() == 3 else coef.expand(len(x), -1, -1)
    msg = torch.einsum("bek,bec,kco->beo", c, x[:, j], weight)
    return torch.zeros(*x.shape[:2], weight.shape[2], dtype=x.dtype).index_add_(1, i, msg)


def case(seed, n, batch, c_in, c_out, K, per_sample, shuffle):
    gen = torch.Generator().manual_seed(seed)
    pos = random_sphere(n, seed, dtype=torch.float64)
    ei, _ = geodesic_radius_graph(pos, 0.5)
    if shuffle:  # edges in no particular order: the plan sorts them
        ei = ei[:, torch.randperm(ei.shape[1], generator=gen)]
    shape = (batch, ei.shape[1], K) if per_sample else (ei.shape[1], K)
    coef = torch.randn(shape, generator=gen).requires_grad_()
    x = torch.randn(batch, n, c_in, generator=gen).requires_grad_()
    w = torch.randn(K, c_in, c_out, generator=gen).requires_grad_()
    return x, w, coef, ei


@pytest.mark.parametrize("c_in, c_out", [(5, 3), (2, 9)])  # mixing first; aggregating first
@pytest.mark.parametrize("per_sample", [False, True])
def test_one_product_equals_the_per_edge_sum_and_the_blockwise_form_with_gradients(
        c_in, c_out, per_sample):
    plan_of = {}
    for call, (n, batch, shuffle) in enumerate([(120, 3, False), (120, 1, True), (90, 4, True),
                                                (120, 3, False)]):
        x, w, coef, ei = case(call, n, batch, c_in, c_out, 3, per_sample, shuffle)
        key = (n, shuffle)  # one plan per graph, reused by the calls on that graph
        if key not in plan_of or not plan_of[key].matches(ei, n):
            plan_of[key] = EdgePlan(ei, n)
        plan = plan_of[key]
        ref = per_edge(x, w, coef, ei)
        wide = wide_aggregate(x, w, coef, plan)
        assert (wide - ref).abs().max() < 1e-12, call
        aggregate.WIDE = False
        try:
            block = aggregate.basis_aggregate(x, w, coef, plan)
        finally:
            aggregate.WIDE = None
        assert (block - ref).abs().max() < 1e-12, call
        g = torch.randn(ref.shape, dtype=ref.dtype)
        want = torch.autograd.grad(ref, (x, w, coef), g)
        for got in (torch.autograd.grad(wide, (x, w, coef), g),
                    torch.autograd.grad(block, (x, w, coef), g)):
            for a, b in zip(got, want):
                assert (a - b).abs().max() < 1e-11 * (1 + b.abs().max()), call


def test_gradcheck_and_partial_gradients():
    x, w, coef, ei = case(7, 40, 2, 3, 4, 2, True, True)
    plan = EdgePlan(ei, 40)
    assert torch.autograd.gradcheck(lambda a, b, c: wide_aggregate(a, b, c, plan), (x, w, coef))
    # a frozen weight and coefficients: only x's gradient, equal to the full one's
    full = torch.autograd.grad(wide_aggregate(x, w, coef, plan).sum(), x)[0]
    only = torch.autograd.grad(wide_aggregate(x, w.detach(), coef.detach(), plan).sum(), x)[0]
    assert torch.equal(full, only)


def test_structures_are_cached_per_batch_size_and_bounded():
    x, w, coef, ei = case(3, 60, 2, 3, 4, 2, False, False)
    plan = EdgePlan(ei, 60)
    for b in range(1, 21):
        y = wide_aggregate(x[:1].expand(b, -1, -1).contiguous(), w, coef, plan)
        assert (y - y[:1]).abs().max() < 1e-12  # the same sample, the same output
    assert 0 < len(plan.wide_cache) <= 16


@pytest.mark.parametrize("c_in, c_out", [(5, 3), (2, 9)])
@pytest.mark.parametrize("wide", [True, False])
def test_int64_indices_give_what_int32_ones_do(monkeypatch, c_in, c_out, wide):
    """The CSR structures take int32 indices (torch's CPU sparse products convert int64
    ones on every product), and int64 past 2**31 entries; a graph that large does not fit
    a test, so the switch is lowered to 0 here. Both forms, with per-sample coefficients
    given as a transposed view (as ``UprightConv`` gives them), and their gradients,
    against the per-edge sum."""
    from usf_graph import sparse

    x, w, coef, ei = case(11, 80, 3, c_in, c_out, 3, True, True)
    ref = per_edge(x, w, coef, ei)
    g = torch.randn(ref.shape, dtype=ref.dtype)
    want = torch.autograd.grad(ref, (x, w, coef), g)
    view = coef.detach().transpose(1, 2).contiguous().transpose(1, 2).requires_grad_()
    for limit, idx in ((2 ** 31, torch.int32), (0, torch.long)):
        monkeypatch.setattr(sparse, "INT32_LIMIT", limit)
        plan = EdgePlan(ei, 80)
        form = wide_aggregate if wide else aggregate.basis_aggregate
        y = form(x, w, view, plan)
        assert (y - ref).abs().max() < 1e-12
        for a, b in zip(torch.autograd.grad(y, (x, w, view), g), want):
            assert (a - b).abs().max() < 1e-11 * (1 + b.abs().max())
        if wide:
            kinds = {key[0] for key in plan.wide_cache}  # forward's and backward's structures
            assert len(kinds) >= 2 and all(s[0].dtype == s[1].dtype == idx
                                           for s in plan.wide_cache.values())
        else:
            assert all(getattr(plan, f"{name}{t}").dtype == idx for t in range(len(plan.bounds))
                       for name in ("crow", "col", "crow_t", "col_t"))


def test_bad_coefficient_shapes_name_the_problem():
    x, w, coef, ei = case(4, 50, 2, 3, 4, 2, False, False)
    plan = EdgePlan(ei, 50)
    with pytest.raises(ValueError, match=r"coef must be"):
        aggregate.basis_aggregate(x, w, coef[:-1], plan)
    with pytest.raises(ValueError, match=r"coef must be"):
        aggregate.basis_aggregate(x, w, coef.detach().expand(3, -1, -1), plan)


@pytest.fixture
def wide_everywhere():
    aggregate.WIDE = True
    yield
    aggregate.WIDE = None


@pytest.mark.parametrize("layer_test", [
    "test_never_stale_fresh_masks_and_fresh_graphs",
    "test_gradcheck_of_the_default_path_in_every_input",
    "test_tiled_plan_matches_the_reference_with_every_gradient",
    "test_pyg_batch_of_different_graphs_equals_each_graph_alone",
    "test_upright_conv_equals_its_dense_reference_with_gradients_on_fresh_masks",
    "test_upright_conv_follows_in_place_edits_of_its_bound_mask_and_weights",
    "test_upright_conv_on_a_pyg_batch_of_different_graphs_equals_each_graph_bound",
])
def test_the_layers_reference_tests_pass_through_the_one_product_form(layer_test, wide_everywhere):
    getattr(test_conv, layer_test)()


def test_a_layer_takes_the_one_product_form_when_asked(wide_everywhere, monkeypatch):
    calls = []
    monkeypatch.setattr(aggregate, "wide_aggregate",
                        lambda *a: calls.append(1) or wide_aggregate(*a))
    pos = random_sphere(80, 1, dtype=torch.float64)
    ei, ew = geodesic_radius_graph(pos, 0.5)
    conv = SphericalConv(3, 4, 0.5).double().bind(ei, ew)
    conv(torch.randn(2, 80, 3, dtype=torch.float64))
    assert calls == [1]
    assert "tiles=not built yet" in repr(conv.plan)  # the one-product form never tiles
    aggregate.WIDE = False
    conv(torch.randn(2, 80, 3, dtype=torch.float64))
    assert calls == [1] and "tiles=1" in repr(conv.plan)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU (CI has none)")
def test_on_a_gpu_the_default_form_equals_the_cpu_blockwise_one():
    """Run where a GPU is: the layers take the one-product form there by default."""
    from usf_graph.nn import UprightConv

    pos = random_sphere(300, 2, dtype=torch.float64)
    ei, ew = geodesic_radius_graph(pos, 0.4)
    gen = torch.Generator().manual_seed(5)
    for conv, c_in in ((SphericalConv(4, 6, 0.4), 4), (SphericalConv(2, 9, 0.4), 2),
                       (UprightConv(4, 6, 0.4), 4)):
        conv = conv.double()
        mask = torch.rand(300, generator=gen) > 0.3
        x = torch.randn(3, 300, c_in, generator=gen)
        up = torch.nn.functional.normalize(torch.randn(3, 3, generator=gen), dim=-1)
        outs, grads = [], []
        for dev in ("cpu", "cuda"):
            c = conv.to(dev)
            kw = {"pos": pos.to(dev)} if isinstance(c, UprightConv) else {}
            c.bind(ei.to(dev), ew.to(dev), mask=mask.to(dev), **kw)
            xd = x.to(dev).requires_grad_()
            y = c(xd, up.to(dev)) if kw else c(xd)
            outs.append(y.cpu())
            grads.append([t.cpu() for t in torch.autograd.grad(y.square().sum(), (xd, c.weight))])
        assert (outs[0] - outs[1]).abs().max() < 1e-12
        for a, b in zip(*grads):
            assert (a - b).abs().max() < 1e-10 * (1 + a.abs().max())
