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
