"""Farthest point sampling and FPSPool: the same points under rigid motions and permutations."""

import math

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.helpers import moved
from usf_graph.nn import FPSPool, euclidean_radius, farthest_point_sampling

FIX = "tests/fixtures/modelnet"


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10_000), st.floats(0.1, 1.0))
def test_fps_picks_the_same_points_under_motion_and_permutation(seed, ratio):
    g = torch.Generator().manual_seed(seed)
    pos = torch.randn(200, 3, generator=g, dtype=torch.float64)
    batch = torch.tensor([0] * 120 + [1] * 80)
    idx = farthest_point_sampling(pos, batch, ratio)
    assert len(idx.unique()) == len(idx) and (batch[idx][:-1] <= batch[idx][1:]).all()
    assert set(farthest_point_sampling(moved(pos, seed), batch, ratio).tolist()) == set(idx.tolist())
    perm = torch.cat([torch.randperm(120, generator=g), 120 + torch.randperm(80, generator=g)])
    idx_p = farthest_point_sampling(pos[perm], batch, ratio)
    assert set(perm[idx_p].tolist()) == set(idx.tolist())
    # farthest-point property: each pick is the farthest from the ones before it
    p0 = pos[idx[batch[idx] == 0]]
    for k in range(1, min(len(p0), 6)):
        d_prev = torch.cdist(pos[:120], p0[:k]).min(1).values
        assert math.isclose(d_prev.max().item(), torch.cdist(p0[k:k + 1], p0[:k]).min().item())


def test_fps_pool_takes_max_within_radius():
    pos = torch.tensor([[0.0, 0, 0], [0.1, 0, 0], [5, 0, 0], [5.1, 0, 0]], dtype=torch.float64)
    x = torch.tensor([[1.0], [7.0], [3.0], [-2.0]], dtype=torch.float64)
    out, pc, bc, idx = FPSPool(ratio=0.5, radius=0.5)(x, pos)
    assert len(idx) == 2 and sorted(out[:, 0].tolist()) == [3.0, 7.0]
    ei, w = euclidean_radius(pos, pos[:1], 0.2)
    assert ei.tolist() == [[0, 1], [0, 0]] and torch.allclose(w, torch.tensor([0, 0.1]).double())
