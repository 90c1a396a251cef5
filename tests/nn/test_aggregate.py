"""The blockwise sparse kernel's kept tiles: reused for the same coefficients, never stale."""

import torch

from tests.nn.test_wide import per_edge
from usf_graph import grids
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
