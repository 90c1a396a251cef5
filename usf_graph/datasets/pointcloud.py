"""Point-cloud datasets: ModelNet from its OFF files, and procedural shapes for offline use."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch
from torch_geometric.data import Data, Dataset

from ..fileio import atomic_torch_save, download
from .stacked import load_or_rebuild, pre_transform_stacked

MODELNET_URL = {"10": "http://3dvision.princeton.edu/projects/2014/3DShapeNets/ModelNet10.zip",
                "40": "http://modelnet.cs.princeton.edu/ModelNet40.zip"}


def read_off(path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``[V, 3]`` float64 and triangles ``[F, 3]`` of an OFF file.

    Accepts the malformed header of many ModelNet files, where "OFF" is joined to the
    counts line (``OFF490 518 0``). Polygons with more than 3 vertices are fanned into
    triangles. Raises ``ValueError`` naming the file and the problem otherwise.
    """
    path = Path(path)
    try:
        lines = [ln.split("#")[0].strip() for ln in path.read_text().splitlines()]
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not a text OFF file ({e})") from None
    lines = [ln for ln in lines if ln]
    if not lines or not lines[0].upper().startswith("OFF"):
        raise ValueError(f"{path}: missing the OFF header; is this an OFF mesh?")
    head = lines[0][3:].split()  # counts joined to "OFF" on the same line
    rest = lines[1:]
    if not head:
        if not rest:
            raise ValueError(f"{path}: missing the counts line 'V F E'")
        head, rest = rest[0].split(), rest[1:]
    try:
        nv, nf = int(head[0]), int(head[1])
    except (ValueError, IndexError):
        raise ValueError(f"{path}: bad counts line {' '.join(head)!r}; expected 'V F E'") from None
    if len(rest) < nv + nf:
        raise ValueError(f"{path}: truncated: header says {nv} vertices and {nf} faces, "
                         f"file has {len(rest)} data lines")
    try:
        verts = np.array([[float(t) for t in ln.split()[:3]] for ln in rest[:nv]])
        faces = []
        for ln in rest[nv:nv + nf]:
            ids = [int(t) for t in ln.split()]
            n, poly = ids[0], ids[1:ids[0] + 1]
            if n < 3 or len(poly) != n:
                raise ValueError
            faces += [(poly[0], poly[k], poly[k + 1]) for k in range(1, n - 1)]
    except ValueError:
        raise ValueError(f"{path}: malformed vertex or face line") from None
    faces = np.array(faces, dtype=np.int64).reshape(-1, 3)
    if verts.shape != (nv, 3) or not np.isfinite(verts).all():
        raise ValueError(f"{path}: vertices must be {nv} finite (x, y, z) triples")
    if len(faces) and (faces.min() < 0 or faces.max() >= nv):
        raise ValueError(f"{path}: a face refers to a vertex outside 0..{nv - 1}")
    return verts, faces


def sample_surface(verts: np.ndarray, faces: np.ndarray, n: int,
                   rng: np.random.Generator) -> np.ndarray:
    """``n`` points uniformly on the mesh surface: faces drawn by area, then uniform
    barycentric coordinates."""
    tri = verts[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not area.sum() > 0:
        raise ValueError("the mesh has no surface area to sample")
    f = rng.choice(len(faces), n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    t = tri[f]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])


class _CloudSet(Dataset):
    """Shared ``get``: clouds stored as ``self.pos [S, N, 3]``, ``self.y [S]``."""

    def len(self) -> int:
        return len(self.y)

    def get(self, idx: int) -> Data:
        d = Data(pos=self.pos[idx], y=self.y[idx:idx + 1])
        if getattr(self, "part", None) is not None:
            d.part = self.part[idx]
        return d


class ModelNet(_CloudSet):
    r"""ModelNet10/40 point clouds sampled from the meshes, a PyG dataset.

    Reads ``root/ModelNet{name}/<class>/{train,test}/*.off`` (the layout of the official
    zip), samples ``num_points`` points per mesh by area (seeded), and stores the split as
    ``pos [S, N, 3]`` float32 and ``y [S]`` under ``root/processed``. Classes are the
    sorted folder names. Missing files are downloaded from ``url`` (default: the official
    zip) and unzipped under ``root``. ``pre_transform`` acts on each ``Data(pos, y)`` before storage
    and must keep ``pos`` ``[N', 3]`` with one ``N'`` (e.g. ``NormalizeScale``).
    """

    def __init__(self, root, name: str = "40", split: str = "train", num_points: int = 1024,
                 seed: int = 0, transform=None, pre_transform=None, url: str | None = None):
        if name not in MODELNET_URL:
            raise ValueError(f"name must be '10' or '40', got {name!r}")
        self.url = url or MODELNET_URL[name]
        if split not in ("train", "test"):
            raise ValueError(f"split must be 'train' or 'test', got {split!r}")
        self.name, self.split, self.num_points, self.seed = name, split, num_points, seed
        super().__init__(str(root), transform, pre_transform, log=False)
        blob = load_or_rebuild(self.processed_paths[0], self.process, ("pos", "y", "classes"))
        self.pos, self.y, self.classes = blob["pos"], blob["y"], blob["classes"].split(",")

    @property
    def raw_dir(self) -> str:
        """The release is read where it is: ``root`` itself."""
        return self.root

    @property
    def raw_file_names(self):
        return [f"ModelNet{self.name}"]

    @property
    def processed_file_names(self):
        return [f"modelnet{self.name}_{self.split}_{self.num_points}_s{self.seed}.pt"]

    def download(self):
        import zipfile

        path = Path(self.root) / f"ModelNet{self.name}.zip"
        try:
            download(self.url, path)
        except FileNotFoundError as e:  # no network: say where the files must go
            raise FileNotFoundError(
                f"ModelNet{self.name} not found under {self.root} and the download failed "
                f"({e}). Get {self.url} and unzip it so that "
                f"{self.root}/ModelNet{self.name}/<class>/{{train,test}}/*.off exist."
            ) from None
        try:
            with zipfile.ZipFile(path) as z:
                z.extractall(self.root)
        except zipfile.BadZipFile:
            raise ValueError(f"{path} is not a valid zip archive; delete it and download "
                             f"{self.url} again") from None
        os.unlink(path)

    def process(self):
        base = Path(self.root) / f"ModelNet{self.name}"
        classes = sorted(p.name for p in base.iterdir() if p.is_dir())
        files = [(f, c) for c, cls in enumerate(classes)
                 for f in sorted((base / cls / self.split).glob("*.off"))]
        if not files:
            raise FileNotFoundError(f"no {self.split} OFF files under {base}/<class>/{self.split}/")
        rng = np.random.default_rng(self.seed)
        pos = torch.from_numpy(np.stack([sample_surface(*read_off(f), self.num_points, rng)
                                         for f, _ in files])).float()
        y = torch.tensor([c for _, c in files])
        if self.pre_transform is not None:
            pos = pre_transform_stacked(self.pre_transform,
                                        (Data(pos=p, y=y[i:i + 1]) for i, p in enumerate(pos)),
                                        "pos")
        atomic_torch_save({"pos": pos, "y": y, "classes": ",".join(classes)},
                          self.processed_paths[0])


# -- procedural shapes ---------------------------------------------------------------------
def _unit(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _box(rng, n, half):
    """Uniform on the surface of a box with half-sizes ``half``; all points flat (1)."""
    a = np.array([half[1] * half[2], half[0] * half[2], half[0] * half[1]])
    axis = rng.choice(3, n, p=a / a.sum())
    p = rng.uniform(-1, 1, (n, 3)) * half
    p[np.arange(n), axis] = np.where(rng.random(n) < 0.5, -1, 1) * half[axis]
    return p, np.ones(n, np.int64)


def _revolve(rng, n, profile, caps):
    """Surface of revolution about z from a profile r(t), z(t), t in [0, 1], sampled by
    area, plus flat disc caps ``[(z, radius), ...]``. Curved part 0, caps 1."""
    t = np.linspace(0, 1, 2001)
    r, z = profile(t)
    seg = np.hypot(np.diff(r), np.diff(z)) * 0.5 * (r[1:] + r[:-1])
    areas = [2 * math.pi * seg.sum()] + [math.pi * rad ** 2 for _, rad in caps]
    k = rng.choice(len(areas), n, p=np.array(areas) / sum(areas))
    out, part = np.empty((n, 3)), (k > 0).astype(np.int64)
    m = k == 0
    i = rng.choice(len(seg), m.sum(), p=seg / seg.sum())
    tt = t[i] + rng.random(m.sum()) * (t[1] - t[0])
    rr, zz = profile(tt)
    ang = rng.uniform(0, 2 * math.pi, m.sum())
    out[m] = np.stack([rr * np.cos(ang), rr * np.sin(ang), zz], 1)
    for c, (zc, rad) in enumerate(caps, 1):
        m = k == c
        rr, ang = rad * np.sqrt(rng.random(m.sum())), rng.uniform(0, 2 * math.pi, m.sum())
        out[m] = np.stack([rr * np.cos(ang), rr * np.sin(ang), np.full(m.sum(), zc)], 1)
    return out, part


def _shape(name: str, rng, n: int):
    j = lambda lo, hi: rng.uniform(lo, hi)  # noqa: E731  (per-sample shape jitter)
    if name == "sphere":
        return _unit(rng, n), np.zeros(n, np.int64)
    if name == "ellipsoid":
        return _unit(rng, n) * [1.0, j(0.45, 0.6), j(0.25, 0.35)], np.zeros(n, np.int64)
    if name == "cube":
        return _box(rng, n, np.array([1.0, 1.0, 1.0]))
    if name == "plate":
        return _box(rng, n, np.array([1.0, j(0.7, 1.0), j(0.08, 0.15)]))
    if name == "cylinder":
        h, r = j(0.8, 1.2), j(0.45, 0.6)
        return _revolve(rng, n, lambda t: (np.full_like(t, r), h * (2 * t - 1)), [(-h, r), (h, r)])
    if name == "cone":
        h, r = j(0.9, 1.2), j(0.6, 0.8)
        return _revolve(rng, n, lambda t: (r * (1 - t), h * (2 * t - 1)), [(-h, r)])
    if name == "capsule":
        h, r = j(0.5, 0.7), j(0.35, 0.45)
        s = 2 * h + math.pi * r  # arc length: hemisphere, side, hemisphere

        def prof(t):
            a = t * s
            lo, hi = a < math.pi * r / 2, a > math.pi * r / 2 + 2 * h
            th = np.where(lo, a / r, np.where(hi, (a - 2 * h) / r, math.pi / 2))
            z = np.where(lo, -h - r * np.cos(th), np.where(hi, h - r * np.cos(th),
                                                           -h + a - math.pi * r / 2))
            return r * np.sin(th), z
        return _revolve(rng, n, prof, [])
    if name == "torus":
        R, r = 1.0, j(0.25, 0.4)
        u, v = rng.uniform(0, 2 * math.pi, (2, 4 * n))
        keep = rng.random(4 * n) < (R + r * np.cos(v)) / (R + r)  # area weighting
        u, v = u[keep][:n], v[keep][:n]
        p = np.stack([(R + r * np.cos(v)) * np.cos(u), (R + r * np.cos(v)) * np.sin(u),
                      r * np.sin(v)], 1)
        return p, np.zeros(n, np.int64)
    if name == "pyramid":
        a, h = 1.0, j(0.9, 1.3)
        apex, base = np.array([0, 0, h]), np.array([[a, a, 0], [-a, a, 0], [-a, -a, 0], [a, -a, 0]])
        tris = [(apex, base[k], base[(k + 1) % 4]) for k in range(4)] + \
               [(base[0], base[1], base[2]), (base[0], base[2], base[3])]
        V = np.array([v for t in tris for v in t])
        return sample_surface(V, np.arange(len(V)).reshape(-1, 3), n, rng), np.ones(n, np.int64)
    if name == "octahedron":
        V = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1.0]])
        V[:, 2] *= j(0.8, 1.3)
        F = [(a, b, c) for a in (0, 1) for b in (2, 3) for c in (4, 5)]
        return sample_surface(V, np.array(F), n, rng), np.ones(n, np.int64)
    raise ValueError(f"unknown shape {name!r}")


SHAPES = ("sphere", "ellipsoid", "cube", "plate", "cylinder", "cone", "capsule", "torus",
          "pyramid", "octahedron")


def make_shape(name: str, num_points: int, rng: np.random.Generator, noise: float = 0.01,
               scale=(0.7, 1.4)) -> tuple[np.ndarray, np.ndarray]:
    """One noisy, randomly scaled shape in its canonical pose: ``(pos [n, 3], part [n])``;
    ``part`` is 1 on flat faces and 0 on curved surface."""
    p, part = _shape(name, rng, num_points)
    p = p * rng.uniform(*scale) + rng.normal(scale=noise, size=p.shape)
    return p, part


class ProceduralShapes(_CloudSet):
    r"""Ten classes of parametric solids (:data:`SHAPES`) with noise and random scale.

    For offline work, the demo and the tests: no files needed. Each sample draws its own
    proportions, scale in [0.7, 1.4] and Gaussian noise (sigma 0.01), deterministically from
    ``seed`` and ``split``. Stores ``pos [S, N, 3]`` (canonical pose), ``y [S]`` and
    ``part [S, N]`` (1 on flat faces, 0 on curved surface) for per-point segmentation.

    Args:
        split: ``train`` or ``test`` (different seeds).
        per_class: samples of each class.
        num_points: points per cloud.
    """

    def __init__(self, split: str = "train", per_class: int = 50, num_points: int = 512,
                 seed: int = 0, transform=None):
        if split not in ("train", "test"):
            raise ValueError(f"split must be 'train' or 'test', got {split!r}")
        super().__init__(None, transform)
        rng = np.random.default_rng([seed, split == "test"])
        pos, part, y = [], [], []
        for c, name in enumerate(SHAPES):
            for _ in range(per_class):
                p, q = make_shape(name, num_points, rng)
                pos.append(p), part.append(q), y.append(c)
        self.classes = list(SHAPES)
        self.pos = torch.from_numpy(np.stack(pos)).float()
        self.part = torch.from_numpy(np.stack(part))
        self.y = torch.tensor(y)
