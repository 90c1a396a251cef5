"""The blockwise sparse kernel's kept tiles: reused for the same coefficients, never stale."""

from functools import partial

import pytest
import torch

from tests.nn.test_wide import case, per_edge
from usf_graph import grids, tracing
from usf_graph.nn import EdgePlan, aggregate, geodesic_radius_graph


def test_tiles_are_kept_for_the_same_coefficients_and_rebuilt_when_they_change(monkeypatch):
    monkeypatch.setattr(aggregate, "WIDE", False)
    gen = torch.Generator().manual_seed(4)
    g = grids.healpix(8)  # nested numbering: narrow halos, so several tiles
    n = len(g)
    ei, _ = geodesic_radius_graph(g.pos, 1.6 * g.spacing)
    ei = ei[:, torch.randperm(ei.shape[1], generator=gen)]  # the plan sorts them
    plan = EdgePlan(ei, n, tile_rows=64)
    assert len(plan.bounds) > 1
    coef = torch.randn(ei.shape[1], 3, generator=gen, dtype=torch.float64)
    w = torch.randn(3, 4, 5, generator=gen, dtype=torch.float64, requires_grad=True)
    for step in range(3):
        x = torch.randn(2, n, 4, generator=gen, dtype=torch.float64, requires_grad=True)
        y = aggregate.basis_aggregate(x, w, coef, plan)
        ref = per_edge(x, w, coef, ei)
        assert (y - ref).abs().max() < 1e-12
        g = torch.autograd.grad(y.square().sum(), (x, w))
        gr = torch.autograd.grad(ref.square().sum(), (x, w))
        assert all((a - b).abs().max() < 1e-12 * b.abs().max() for a, b in zip(g, gr))
        assert plan.tiles(coef) is plan.tiles(coef)  # kept: the same tensor, same version
        kept = plan.tiles(coef)
        if step == 0:
            coef.mul_(-2.0)  # edited in place: the next call must not read the old tiles
        else:
            coef = coef.clone()  # equal values in a new tensor: new tiles, same answer
        assert plan.tiles(coef) is not kept
    scratch = torch.randn(ei.shape[1], 3, generator=gen, dtype=torch.float64)
    plan.tiles(scratch)
    assert plan._memo[False][0]() is scratch
    del scratch  # coefficients that can never come back: their tiles are freed with them
    assert False not in plan._memo


@pytest.mark.parametrize("c_in, c_out", [(5, 3), (2, 9)])
@pytest.mark.parametrize("per_sample", [False, True])
def test_plain_form_equals_the_per_edge_sum_with_gradients(c_in, c_out, per_sample):
    """The form an export traces (padded rows, batched products) against the per-edge
    reference, on new graphs, sorted or not, with gradients in x, weights and coefficients."""
    for call, (n, batch, shuffle) in enumerate([(120, 3, False), (90, 1, True), (120, 2, True)]):
        x, w, coef, ei = case(10 + call, n, batch, c_in, c_out, 3, per_sample, shuffle)
        plan = EdgePlan(ei, n)
        with tracing.plain():
            got = aggregate.basis_aggregate(x, w, coef, plan)
        ref = per_edge(x, w, coef, ei)
        assert (got - ref).abs().max() < 1e-12, call
        g = torch.randn(ref.shape, dtype=ref.dtype)
        for a, b in zip(torch.autograd.grad(got, (x, w, coef), g),
                        torch.autograd.grad(ref, (x, w, coef), g)):
            assert (a - b).abs().max() < 1e-11 * (1 + b.abs().max()), call
        assert plan.pad_col.dtype == torch.int32  # kept for the next call on this graph


def _penalty_gradients(fn, x, w, coef, g):
    """The gradient of a gradient penalty: ``|d<f, g>/d(x, w, coef)|^2`` differentiated again."""
    first = torch.autograd.grad((fn(x, w, coef) * g).sum(), (x, w, coef), create_graph=True)
    return torch.autograd.grad(sum(t.square().sum() for t in first), (x, w, coef, g))


@pytest.mark.parametrize("wide", [False, True], ids=["blockwise", "wide"])
@pytest.mark.parametrize("per_sample", [False, True])
def test_second_derivatives_of_both_forms_equal_the_per_edge_sums(wide, per_sample):
    """``create_graph=True`` (gradient penalties, Hessian-vector products) through the fast
    forms: their gradients are differentiable again, in the inputs and in the incoming
    gradient, and equal the per-edge reference's, on new graphs, sorted or not."""
    for call, (n, batch, shuffle) in enumerate([(80, 2, False), (60, 1, True)]):
        x, w, coef, ei = case(20 + call, n, batch, 4, 3, 2, per_sample, shuffle)
        plan = EdgePlan(ei, n)
        g = torch.randn(batch, n, 3, dtype=x.dtype, generator=torch.Generator().manual_seed(call))
        g.requires_grad_()
        aggregate.WIDE = wide
        try:
            got = _penalty_gradients(partial(aggregate.basis_aggregate, plan=plan),
                                     x, w, coef, g)
            if call == 1:
                sub = case(30, 12, 1, 2, 2, 2, per_sample, True)
                small = EdgePlan(sub[3], 12)
                assert torch.autograd.gradgradcheck(
                    partial(aggregate.basis_aggregate, plan=small), sub[:3])
        finally:
            aggregate.WIDE = None
        want = _penalty_gradients(partial(per_edge, edge_index=ei), x, w, coef, g)
        for a, b in zip(got, want):
            assert (a - b).abs().max() < 1e-11 * (1 + b.abs().max()), call
