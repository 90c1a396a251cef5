"""Point-cloud datasets: OFF files, ModelNet's layout, procedural shapes."""


import numpy as np
import pytest
import torch

from usf_graph.datasets import SHAPES, ModelNet, ProceduralShapes, read_off, sample_surface

FIX = "tests/fixtures/modelnet"


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
    torch.save({"pos": train.pos}, train.processed_paths[0])  # a stale file, lacking y: made again
    with pytest.warns(UserWarning, match=r"missing \['classes', 'y'\].*processing it again"):
        remade = ModelNet(tmp_path, "10", "train", num_points=64)
    assert torch.equal(remade.pos, train.pos) and remade.y.tolist() == [0, 1, 1]
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
