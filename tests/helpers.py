"""Helpers shared by the tests: paths, repository scripts as modules, fixture writers."""

import gzip
import importlib.util
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / "tests" / "fixtures"


def load_script(rel: str):
    """A script of the repository (``examples/x.py``, ``datasets/y/prepare.py``) as a module."""
    spec = importlib.util.spec_from_file_location(rel.replace("/", "_")[:-3], ROOT / rel)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def write_idx(path, arr, gz=False):
    """An MNIST IDX file (big-endian header, uint8 data), optionally gzipped."""
    arr = np.asarray(arr, np.uint8)
    magic = 2051 if arr.ndim == 3 else 2049
    head = magic.to_bytes(4, "big") + len(arr).to_bytes(4, "big")
    if arr.ndim == 3:
        head += arr.shape[1].to_bytes(4, "big") + arr.shape[2].to_bytes(4, "big")
    data = head + arr.tobytes()
    with (gzip.open if gz else open)(path, "wb") as f:
        f.write(data)


def random_sphere(n, seed, dtype=None):
    """``n`` seeded random unit vectors."""
    import torch

    g = torch.Generator().manual_seed(seed)
    p = torch.randn(n, 3, generator=g, dtype=dtype or torch.get_default_dtype())
    return p / p.norm(dim=1, keepdim=True)


def moved(pos, seed):
    """``pos`` under a seeded random rigid motion (rotation and translation)."""
    import torch

    from usf_graph.geometry import random_rotation

    R = random_rotation(seed=seed)
    t = torch.randn(3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) * 3
    return pos @ R.T + t


def tiny_seg_checkpoint(path, **config):
    """A seeded untrained spherical U-Net (icosahedral:3, gravity) saved as a segmentation
    checkpoint at ``path``, its head scaled so that its labels are confident; ``config``
    adds to the saved config (e.g. ``size``). Returns the model."""
    import torch

    from usf_graph.models import SphericalUNet
    from usf_graph.train import save_checkpoint

    torch.manual_seed(0)
    seg = SphericalUNet(13, level=3, channels=(8, 8, 8, 8), gravity=True)
    with torch.no_grad():
        seg.head.weight.mul_(30)
    save_checkpoint(path, seg, {"model": "spherical_unet", **config, **seg.config}, {})
    return seg


def decode_video(path):
    """Every frame of a video as OpenCV decodes it (RGB), and its frame rate."""
    from usf_graph import videos

    return [f for _, f in videos.frames(path)], videos.info(path)[0]


class CodeOnLoad:
    """A pickle that runs code when loaded: it creates the file ``mark``. A reader that
    refuses it unrun leaves ``mark`` missing."""

    def __init__(self, mark):
        self.mark = mark

    def __reduce__(self):
        return (Path.touch, (self.mark,))
