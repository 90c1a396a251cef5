"""PointCloudNet: rigid-motion invariance in float64; the PointNet baseline is not invariant."""


import pytest
import torch

from tests.helpers import moved
from usf_graph.datasets import ProceduralShapes
from usf_graph.models import PointCloudNet, PointNet

FIX = "tests/fixtures/modelnet"


@pytest.fixture(scope="module")
def clouds():
    d = ProceduralShapes("test", per_class=1, num_points=300, seed=1)
    return d.pos.double()[[0, 2, 5, 7]]


@pytest.mark.parametrize("segmentation", [False, True])
def test_logits_invariant_to_rigid_motions_in_float64(clouds, segmentation):
    torch.manual_seed(0)
    net = PointCloudNet(10, segmentation=segmentation).double().eval()
    ref = net(clouds)
    for seed in range(4):
        out = net(moved(clouds, seed))
        assert (out - ref).abs().max() < 1e-9, seed
    assert ref.std() > 1e-3  # not a constant output
    # and, by default, to the cloud's scale (radii in RMS radii); one pooling between stages
    assert (net(2.5 * clouds) - ref).abs().max() < 1e-9 and len(net.pools) == 2
    perm = torch.randperm(clouds.shape[1])
    out = net(clouds[:, perm])
    assert torch.allclose(out, ref[:, perm] if segmentation else ref, atol=1e-10, rtol=0)


def test_baseline_is_not_invariant(clouds):
    torch.manual_seed(0)
    net = PointNet(10).double().eval()
    assert (net(moved(clouds, 0)) - net(clouds)).abs().max() > 1e-2


def test_segmentation_labels_move_with_points(clouds):
    net = PointCloudNet(2, segmentation=True).double().eval()
    pos = clouds[0]
    out = net(pos, torch.zeros(len(pos), dtype=torch.long))
    assert out.shape == (len(pos), 2)
    perm = torch.randperm(len(pos))
    assert torch.allclose(net(moved(pos, 3)[perm]), out[perm], atol=1e-10, rtol=0)


def test_segmentation_interpolates_from_the_three_nearest_centres_by_inverse_square_distance():
    """Features reach the fine points from the 3 nearest coarse ones of the same cloud,
    weighted by 1 / d^2: against a brute-force search."""
    from usf_graph.models.pointcloud import _interpolate

    g = torch.Generator().manual_seed(4)
    pos, pos_f = torch.rand(20, 3, generator=g, dtype=torch.float64), torch.rand(30, 3, generator=g, dtype=torch.float64)
    batch, batch_f = torch.arange(20) // 10, torch.arange(30) // 15
    x = torch.randn(20, 4, generator=g, dtype=torch.float64)
    got = _interpolate(x, pos, batch, pos_f, batch_f)
    for i in range(30):
        same = torch.nonzero(batch == batch_f[i])[:, 0]
        d2 = ((pos[same] - pos_f[i]) ** 2).sum(-1)
        near = same[d2.argsort()[:3]]
        w = 1 / ((pos[near] - pos_f[i]) ** 2).sum(-1)
        torch.testing.assert_close(got[i], (w[:, None] * x[near]).sum(0) / w.sum())
