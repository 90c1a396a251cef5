"""The dataset preparation scripts: download (from file:// mirrors here), verify, process."""

import shutil
import zipfile

import numpy as np
import pytest
import torch

import usf_graph.datasets.mnist as mnist_module
from tests.helpers import ROOT, write_idx
from tests.helpers import load_script as script
from usf_graph.datasets import download_mnist
from usf_graph.datasets.mnist import IDX_FILES, lift_digits
from usf_graph.fileio import download, file_md5
from usf_graph.grids import icosahedral


@pytest.fixture
def mirror(tmp_path, monkeypatch):
    """A folder laid out like an MNIST mirror (7 real-format digits per split)."""
    rng = np.random.default_rng(0)
    imgs = (rng.random((7, 28, 28)) * 255).astype(np.uint8)
    labs = np.arange(7) % 10
    m = tmp_path / "mirror"
    m.mkdir()
    for img_name, lab_name in IDX_FILES.values():
        write_idx(m / f"{img_name}.gz", imgs, gz=True)
        write_idx(m / f"{lab_name}.gz", labs, gz=True)
    monkeypatch.setattr(mnist_module, "MNIST_MD5", {p.name: file_md5(p) for p in m.iterdir()})
    return m, imgs, labs


def test_mnist_prepare_downloads_verifies_and_builds_splits(tmp_path, mirror):
    m, imgs, labs = mirror
    root = tmp_path / "root"
    prep = script("datasets/spherical_mnist/prepare.py")
    sets = prep.main(["--root", str(root), "--mirror", (tmp_path / "gone").as_uri(),
                      "--mirror", m.as_uri(), "--grid", "icosahedral:1", "--test-rotate", "none", "so3"])
    for p in m.iterdir():  # the second mirror served every file, byte for byte
        assert (root / p.name).read_bytes() == p.read_bytes()
    ds = sets[("test", "none")]
    assert torch.equal(ds.y, torch.as_tensor(labs))
    assert torch.equal(ds.x, lift_digits(imgs, icosahedral(1).pos.numpy(), None, False))
    assert sorted(sets) == [("test", "none"), ("test", "so3"), ("train", "none")]
    assert not torch.equal(sets[("test", "so3")].x, ds.x)
    # files already there with the right checksum are kept: no mirror needed
    assert len(download_mnist(root, mirrors=((tmp_path / "gone").as_uri(),))) == 4


def test_mnist_download_rejects_corrupt_and_missing_files(tmp_path, mirror):
    m, _, _ = mirror
    bad = tmp_path / "bad"
    shutil.copytree(m, bad)
    (bad / "t10k-labels-idx1-ubyte.gz").write_bytes(b"not what was published")
    root = tmp_path / "root"
    with pytest.raises(FileNotFoundError, match="no mirror served t10k-labels-idx1-ubyte.gz") as e:
        download_mnist(root, mirrors=(bad.as_uri(),), progress=False)
    assert "expected" in str(e.value)  # the MD5 mismatch is named
    assert not (root / "t10k-labels-idx1-ubyte.gz").exists()
    assert not any(p.name.endswith(".tmp") for p in root.iterdir())  # nothing partial left
    with pytest.raises(FileNotFoundError, match="Download it by hand"):
        download((tmp_path / "none.gz").as_uri(), tmp_path / "x.gz", progress=False)


def test_modelnet_prepare_downloads_and_unzips(tmp_path):
    z = tmp_path / "ModelNet10.zip"
    with zipfile.ZipFile(z, "w") as f:
        for p in (ROOT / "tests/fixtures/modelnet").rglob("*.off"):
            f.write(p, p.relative_to(ROOT / "tests/fixtures/modelnet"))
    prep = script("datasets/modelnet/prepare.py")
    sets = prep.main(["--root", str(tmp_path / "mn"), "--name", "10", "--num-points", "32",
                      "--url", z.as_uri()])
    assert len(sets["train"]) == 3 and len(sets["test"]) == 2
    assert sets["train"].classes == ["chair", "table"] and sets["train"].pos.shape == (3, 32, 3)
    assert not (tmp_path / "mn" / "ModelNet10.zip").exists()  # unzipped, then removed
    bad = tmp_path / "bad.zip"
    bad.write_bytes(b"PK garbage")
    with pytest.raises(ValueError, match="not a valid zip"):
        prep.main(["--root", str(tmp_path / "mn2"), "--name", "10", "--url", bad.as_uri()])
