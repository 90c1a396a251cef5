r"""Stanford 2D-3D-S panoramas (Armeni et al. 2017) for semantic segmentation, as a PyG dataset.

Reads the released layout::

    root/semantic_labels.json     # or root/assets/semantic_labels.json
    root/area_{1,2,3,4,5a,5b,6}/pano/rgb/camera_<id>_<room>_<n>_frame_equirectangular_domain_rgb.png
    root/area_*/pano/semantic/camera_<id>_<room>_<n>_frame_equirectangular_domain_semantic.png

A semantic PNG stores, per pixel, an index ``R * 65536 + G * 256 + B`` into
``semantic_labels.json``, whose entries are named ``<class>_<instance>_<room>_...``; the
class is the name before the first ``_``. A pixel is ignored (label 255) when its entry is
``<UNK>`` (entry 0, also what black borders decode to), when its index is past the end of
the list (the colour 0x0D0D0D marks missing data), or when its class is not one of the 13.
Other codebases differ: torch-harmonics maps 0x0D0D0D to clutter; HoHoNet-style loaders
read ``G * 256 + B`` and treat R != 0 as unknown (the same for valid entries).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from torch_geometric.data import Dataset
from tqdm.auto import tqdm

from ..cameras import Equirectangular
from ..fileio import atomic_torch_save
from ..frontend import SphericalFrontend
from ..frontend.image import SphericalImage
from ..grids import Grid, from_spec
from ..scenes import IGNORE, SEMANTIC_CLASSES
from ..scenes.export import STANFORD_AREAS, STANFORD_MISSING
from .stacked import (
    UprightAsReleased,
    load_or_rebuild,
    missing_release,
    pre_transform_stacked,
    read_release_image,
)

AREAS = STANFORD_AREAS
#: The three area-disjoint folds: (train areas, test areas).
FOLDS = {1: (("1", "2", "3", "4", "6"), ("5a", "5b")),
         2: (("1", "3", "5a", "5b", "6"), ("2", "4")),
         3: (("2", "4", "5a", "5b"), ("1", "3", "6"))}
MISSING = STANFORD_MISSING  # the colour of pixels without data
GET_IT = ("Stanford 2D-3D-S is distributed by its authors on request (https://github.com/alexsax/"
          "2D-3D-Semantics: fill in the form, then download the area_*_no_xyz archives; the "
          "original S3 bucket is gone). Unpack them so that {root}/area_1/pano/rgb/ etc. exist, "
          "and put assets/semantic_labels.json from that repository at {root}/semantic_labels.json.")


def label_table(path) -> np.ndarray:
    """``semantic_labels.json`` -> ``[E]`` uint8: the class index (0..12, alphabetical) of
    each entry, 255 for ``<UNK>`` and names outside the 13 classes."""
    path = Path(path)
    try:
        names = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"{path} is not a readable semantic_labels.json: {e}") from e
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise ValueError(f"{path} must be a JSON list of strings like 'chair_1_office_1_0'")
    lut = {c: i for i, c in enumerate(SEMANTIC_CLASSES)}
    return np.array([lut.get(n.split("_", 1)[0], IGNORE) for n in names], np.uint8)


def decode_semantic(rgb: np.ndarray, table: np.ndarray) -> np.ndarray:
    """A semantic PNG as RGB ``[H, W, 3]`` uint8 -> labels ``[H, W]`` uint8 (255: ignored,
    see the module docstring)."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[-1] < 3 or rgb.dtype != np.uint8:
        raise ValueError(f"a semantic image must be RGB uint8 [H, W, 3], got {rgb.dtype} {rgb.shape}")
    idx = (rgb[..., 0].astype(np.int64) << 16) | (rgb[..., 1].astype(np.int64) << 8) | rgb[..., 2]
    out = np.full(idx.shape, IGNORE, np.uint8)
    ok = idx < len(table)  # also drops MISSING, which is past the end of the real list
    out[ok] = table[idx[ok]]
    out[idx == MISSING] = IGNORE
    return out


def panoramas(root, areas) -> list[tuple[Path, Path]]:
    """``(rgb, semantic)`` paths of every panorama of ``areas``, sorted; a missing area or a
    semantic PNG without its RGB raises with download instructions."""
    root, out = Path(root), []
    for a in areas:
        sem_dir = root / f"area_{a}" / "pano" / "semantic"
        if not sem_dir.is_dir():
            raise FileNotFoundError(f"{sem_dir} not found. " + GET_IT.format(root=root))
        for sem in sorted(sem_dir.glob("*_domain_semantic.png")):
            rgb = root / f"area_{a}" / "pano" / "rgb" / sem.name.replace("_semantic.png", "_rgb.png")
            if not rgb.is_file():
                raise FileNotFoundError(f"{rgb} is missing (its semantic image exists). "
                                        + GET_IT.format(root=root))
            out.append((rgb, sem))
    return out


class Stanford2D3DS(UprightAsReleased, Dataset):
    r"""Stanford 2D-3D-S panoramas lifted to a spherical grid, with per-point labels.

    Args:
        root: the dataset folder (layout in the module docstring); processed tensors go to
            ``root/processed``.
        fold: 1, 2 or 3, the area-disjoint folds (:data:`FOLDS`).
        split: ``train`` or ``test``.
        grid: grid spec or :class:`~usf_graph.grids.Grid`.
        size: panoramas are resized to ``2 size x size`` first (area averaging for RGB,
            nearest for labels); the stored ``image`` and ``label_image`` have that size.

    A sample has the fields of :class:`~usf_graph.datasets.RoomsSegmentation`: ``x [N, 3]``
    (RGB in [0, 1]), ``y [N]`` (0..12, 255 ignored), ``mask``, ``pos``, ``area``,
    ``image [1, size, 2 size, 3]`` and ``label_image [1, size, 2 size]``; the split in
    static form as ``dataset.x``, ``dataset.y``, ... and the panorama names in
    ``dataset.names``.
    """

    def __init__(self, root, fold: int = 1, split: str = "train", grid="icosahedral:5",
                 size: int = 256, transform=None, pre_transform=None, progress: bool = True):
        if fold not in FOLDS:
            raise ValueError(f"fold must be 1, 2 or 3, got {fold!r}")
        if split not in ("train", "test"):
            raise ValueError(f"split must be 'train' or 'test', got {split!r}")
        self.fold, self.split, self.size, self.progress = fold, split, int(size), progress
        self.areas = FOLDS[fold][0 if split == "train" else 1]
        self.grid: Grid = from_spec(grid) if isinstance(grid, str) else grid
        self.camera = Equirectangular(2 * self.size, self.size)
        self.frontend = SphericalFrontend(self.camera, self.grid)
        self._labels_json = next((p for p in (Path(root) / "semantic_labels.json",
                                              Path(root) / "assets" / "semantic_labels.json")
                                  if p.is_file()), None)
        if self._labels_json is None:
            raise FileNotFoundError(f"semantic_labels.json not found under {root}. "
                                    + GET_IT.format(root=root))
        super().__init__(str(root), transform, pre_transform, log=False)
        blob = load_or_rebuild(self.processed_paths[0], self.process,
                               ("x", "y", "image", "label_image", "names"))
        for k, v in blob.items():
            setattr(self, k, v)
        self.mask = self.frontend.mask[None].expand(len(self.x), -1)

    @property
    def raw_dir(self) -> str:
        """The release is read where it is: ``root`` itself."""
        return self.root

    @property
    def raw_file_names(self):
        return [f"area_{a}" for a in self.areas]

    @property
    def processed_file_names(self):
        spec = self.grid.spec.replace(":", "").replace(",", "_")
        return [f"stanford_f{self.fold}_{self.split}_{spec}_{self.size}.pt"]

    def download(self):
        raise missing_release(self, GET_IT.format(root=self.root))

    def process(self):
        import cv2

        table = label_table(self._labels_json)
        labels_fe = SphericalFrontend(self.camera, self.grid, interpolation="nearest")
        W, H = self.camera.width, self.camera.height
        xs, ys, imgs, labs, names = [], [], [], [], []
        for rgb_path, sem_path in tqdm(panoramas(self.root, self.areas),
                                       desc=f"lifting Stanford 2D-3D-S fold {self.fold} {self.split}",
                                       disable=not self.progress, leave=False):
            get_it = GET_IT.format(root=self.root)
            rgb = read_release_image(rgb_path, cv2.IMREAD_COLOR, get_it)[..., ::-1]  # no alpha
            sem = read_release_image(sem_path, cv2.IMREAD_COLOR, get_it)[..., ::-1]
            if rgb.shape != sem.shape or rgb.shape[1] != 2 * rgb.shape[0]:
                raise ValueError(f"{rgb_path.name} is {rgb.shape[1]}x{rgb.shape[0]} and its semantic "
                                 f"image {sem.shape[1]}x{sem.shape[0]}; both must be the same 2:1 "
                                 "equirectangular size (4096x2048 as released)")
            label = decode_semantic(np.ascontiguousarray(sem), table)
            rgb = cv2.resize(np.ascontiguousarray(rgb), (W, H), interpolation=cv2.INTER_AREA)
            label = cv2.resize(label, (W, H), interpolation=cv2.INTER_NEAREST)
            xs.append(self.frontend.lift(rgb.astype(np.float32) / 255))
            ys.append(labels_fe.lift(label)[:, 0].round().long())
            imgs.append(rgb)
            labs.append(label)
            names.append(rgb_path.name.split("_frame_")[0])
        if not xs:
            raise FileNotFoundError(f"no panoramas in areas {self.areas} under {self.root}. "
                                    + GET_IT.format(root=self.root))
        x = torch.stack(xs).to(torch.float16)
        y = torch.stack(ys).masked_fill(~self.frontend.mask, IGNORE)
        if self.pre_transform is not None:
            x = pre_transform_stacked(self.pre_transform,
                                      (self._sample(xi.float(), y[i]) for i, xi in enumerate(x)),
                                      "x", fixed=("pos",)).to(torch.float16)
        atomic_torch_save({"x": x, "y": y, "image": torch.as_tensor(np.stack(imgs)),
                           "label_image": torch.as_tensor(np.stack(labs)), "names": names},
                          self.processed_paths[0])

    def len(self) -> int:
        return len(self.x)

    def _sample(self, x, y) -> SphericalImage:
        return SphericalImage(x=x, y=y, pos=self.grid.pos.float(), area=self.grid.area.float())

    def get(self, idx: int) -> SphericalImage:
        d = self._sample(self.x[idx].float(), self.y[idx])
        d.mask = self.frontend.mask.clone()
        d.image = self.image[idx][None]
        d.label_image = self.label_image[idx][None]
        return d

    def __repr__(self) -> str:
        return (f"Stanford2D3DS({len(self)}, fold={self.fold}, split={self.split}, "
                f"grid={self.grid.spec}, size={self.size})")


__all__ = ["Stanford2D3DS", "FOLDS", "label_table", "decode_semantic", "panoramas"]
