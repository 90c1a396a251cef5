import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from usf_graph.datasets import SHAPES, ModelNet, ProceduralShapes, read_off, sample_surface
from usf_graph.geometry import random_rotation
from usf_graph.models import PointCloudNet, PointNet
from usf_graph.nn import FPSPool, euclidean_radius, farthest_point_sampling

FIX = "tests/fixtures/modelnet"


def moved(pos, seed):
    R = random_rotation(seed=seed)
    t = torch.randn(3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) * 3
    return pos @ R.T + t


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


def test_read_off_standard_and_malformed_header():
    v, f = read_off(f"{FIX}/ModelNet10/chair/train/chair_0001.off")
    assert v.shape == (8, 3) and f.shape == (12, 3)  # 6 quads fanned into 12 triangles
    v, f = read_off(f"{FIX}/ModelNet10/table/train/table_0001.off")  # "OFF4 4 0"
    assert v.shape == (4, 3) and f.shape == (4, 3) and v[3, 2] == 2
    p = sample_surface(*read_off(f"{FIX}/ModelNet10/chair/train/chair_0001.off"), 4000,
                       np.random.default_rng(0))
    on_face = np.isclose(p, 0) | np.isclose(p, 1)
    assert on_face.any(1).all() and ((p >= -1e-12) & (p <= 1 + 1e-12)).all()
    # area weighting: each of the 6 unit faces gets about 1/6 of the points
    counts = np.array([np.isclose(p[:, a], s).sum() for a in range(3) for s in (0, 1)])
    assert np.abs(counts / 4000 - 1 / 6).max() < 0.03


@pytest.mark.parametrize("text, msg", [
    ("", "OFF header"), ("PLY\n", "OFF header"), ("OFF\n", "counts"),
    ("OFF\nthree 1 0\n", "counts"), ("OFF\n3 1 0\n0 0 0\n1 0 0\n", "truncated"),
    ("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n", "outside"),
    ("OFF\n3 1 0\n0 0 0\n1 0 x\n0 1 0\n3 0 1 2\n", "malformed"),
    ("OFF\n3 1 0\n0 0 0\n1 0 nan\n0 1 0\n3 0 1 2\n", "finite"),
])
def test_read_off_rejects_corrupt_files(tmp_path, text, msg):
    p = tmp_path / "bad.off"
    p.write_text(text)
    with pytest.raises(ValueError, match=msg):
        read_off(p)


def test_modelnet_dataset_reads_the_official_layout(tmp_path):
    import shutil

    shutil.copytree(FIX, tmp_path, dirs_exist_ok=True)
    train = ModelNet(tmp_path, "10", "train", num_points=64)
    assert train.classes == ["chair", "table"] and train.y.tolist() == [0, 1, 1]
    assert train.pos.shape == (3, 64, 3) and train[2].pos.shape == (64, 3)
    assert ModelNet(tmp_path, "10", "test", num_points=64).y.tolist() == [0, 1]
    again = ModelNet(tmp_path, "10", "train", num_points=64)  # from processed/
    assert torch.equal(again.pos, train.pos)
    with pytest.raises(FileNotFoundError, match="ModelNet40"):
        ModelNet(tmp_path / "empty", "40")
    from torch_geometric.transforms import FixedPoints, NormalizeScale

    shutil.copytree(FIX, tmp_path / "n", dirs_exist_ok=True)
    norm = ModelNet(tmp_path / "n", "10", "train", num_points=64, pre_transform=NormalizeScale())
    centred = train.pos - train.pos.mean(1, keepdim=True)
    scale = centred.abs().amax((1, 2), keepdim=True)
    torch.testing.assert_close(norm.pos, centred / scale, rtol=0, atol=1e-5)
    shutil.copytree(FIX, tmp_path / "f", dirs_exist_ok=True)
    fewer = ModelNet(tmp_path / "f", "10", "train", num_points=64, pre_transform=FixedPoints(16))
    assert fewer.pos.shape == (3, 16, 3)


def test_procedural_shapes_are_deterministic_and_labelled():
    a, b = ProceduralShapes("train", 2, 128, seed=3), ProceduralShapes("train", 2, 128, seed=3)
    assert torch.equal(a.pos, b.pos) and len(a) == 2 * len(SHAPES)
    assert not torch.equal(a.pos, ProceduralShapes("test", 2, 128, seed=3).pos)
    sphere = a.pos[0].double()
    r = sphere.norm(dim=1)
    assert (r.std() / r.mean()) < 0.03  # noisy sphere of one radius
    assert a.part[a.y == SHAPES.index("cube")].all() and not a.part[a.y == 0].any()
    cyl = a.part[a.y == SHAPES.index("cylinder")].float().mean()
    assert 0.1 < cyl < 0.4  # caps are a minority of a cylinder's area
