r"""PANDORA (Xu et al., ECCV 2022): indoor panoramas with spherical boxes, as a PyG dataset.

Reads the released layout::

    root/images/<file_name>              # 1920 x 960 equirectangular JPGs
    root/annotations/{train,test}.json   # COCO-like: images, annotations, categories

An annotation's ``bbox`` is ``[lon, lat, fov_x, fov_y, gamma]`` in degrees, in the image's
terms (longitude grows to the right), converted here to usf-graph's boxes
(:func:`usf_graph.ops.from_pandora`); ``category_id`` 1..47 becomes ``box_class`` 0..46.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from torch_geometric.data import Dataset
from tqdm.auto import tqdm

from ..cameras import Equirectangular
from ..fileio import atomic_torch_save, decode_image
from ..frontend import SphericalFrontend
from ..frontend.image import SphericalImage
from ..grids import Grid, from_spec
from ..ops import from_pandora
from .stacked import (
    UprightAsReleased,
    add_boxes,
    load_or_rebuild,
    missing_release,
    pack_boxes,
    pre_transform_stacked,
)

GET_IT = ("PANDORA is distributed by its authors (https://github.com/tdsuper/SphericalObjectDetection); "
          "download it there and unpack it so that {root}/images/ holds the panoramas and "
          "{root}/annotations/{split}.json the boxes.")


def read_annotations(path) -> dict:
    """A PANDORA annotation file -> ``{file_name: (boxes [K, 5] radians, classes [K])}``,
    with clear errors for missing keys, bad boxes and category ids outside 1..47."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
        images, anns = doc["images"], doc["annotations"]
    except (json.JSONDecodeError, KeyError, TypeError) as e:
        raise ValueError(f"{path} is not a PANDORA annotation file (COCO-like JSON with 'images' "
                         f"and 'annotations'): {e}") from e
    names = {im["id"]: im["file_name"] for im in images}
    out = {n: ([], []) for n in names.values()}
    for a in anns:
        box, cat = a.get("bbox"), a.get("category_id")
        where = f"annotation {a.get('id')} of {path.name}"
        if a.get("image_id") not in names:
            raise ValueError(f"{where} refers to image {a.get('image_id')}, which is not listed")
        if not isinstance(box, list) or len(box) != 5 or not np.all(np.isfinite(np.asarray(box, float))):
            raise ValueError(f"{where} has bbox {box}; PANDORA boxes are 5 finite numbers "
                             f"[lon, lat, fov_x, fov_y, gamma] in degrees")
        if not -90 <= box[1] <= 90 or not (0 < box[2] < 180 and 0 < box[3] < 180):
            raise ValueError(f"{where} has bbox {box}; PANDORA boxes have lat in [-90, 90] and "
                             f"fields of view in (0, 180) degrees (a box is bounded by great "
                             f"circles); correct or remove that annotation")
        if not isinstance(cat, int) or not 1 <= cat <= 47:
            raise ValueError(f"{where} has category_id {cat}; PANDORA's are 1..47")
        out[names[a["image_id"]]][0].append(box)
        out[names[a["image_id"]]][1].append(cat - 1)
    return {n: (from_pandora(np.asarray(b, np.float64).reshape(-1, 5)), np.asarray(c, np.int64))
            for n, (b, c) in out.items()}


class Pandora(UprightAsReleased, Dataset):
    r"""PANDORA panoramas lifted to a spherical grid, with their spherical boxes.

    Args:
        root: the dataset folder (layout in the module docstring); processed tensors go to
            ``root/processed``.
        split: ``train`` or ``test``.
        grid: grid spec or :class:`~usf_graph.grids.Grid`.
        interpolation: how the 1920 x 960 images are lifted (``area`` averages the pixels of
            each grid cell, right for grids coarser than the image).

    A sample has ``x [N, 3]`` (RGB in [0, 1]), ``pos``, ``area``, ``boxes [K, 5]`` (radians,
    usf-graph's convention) and ``box_class [K]`` (0..46, PANDORA's order).
    """

    def __init__(self, root, split: str = "train", grid="icosahedral:5",
                 interpolation: str = "area", transform=None, pre_transform=None,
                 progress: bool = True):
        if split not in ("train", "test"):
            raise ValueError(f"split must be 'train' or 'test', got {split!r}")
        self.split, self.interpolation, self.progress = split, interpolation, progress
        self.grid: Grid = from_spec(grid) if isinstance(grid, str) else grid
        ann = Path(root) / "annotations" / f"{split}.json"
        if not ann.exists():
            raise FileNotFoundError(f"{ann} not found. " + GET_IT.format(root=root, split=split))
        super().__init__(str(root), transform, pre_transform, log=False)
        blob = load_or_rebuild(self.processed_paths[0], self.process, ("x", "boxes", "box_class", "box_ptr"))
        self.x, self.boxes, self.box_class, self.box_ptr = (blob[k] for k in ("x", "boxes", "box_class", "box_ptr"))

    @property
    def raw_dir(self) -> str:
        """The release is read where it is: ``root`` itself."""
        return self.root

    @property
    def raw_file_names(self):
        return [f"annotations/{self.split}.json"]

    @property
    def processed_file_names(self):
        spec = self.grid.spec.replace(":", "").replace(",", "_")
        return [f"pandora_{self.split}_{spec}_{self.interpolation}.pt"]

    def download(self):
        raise missing_release(self, GET_IT.format(root=self.root, split=self.split))

    def process(self):
        import cv2

        anns = read_annotations(self.raw_paths[0])
        fe, xs, boxes, classes = None, [], [], []
        for name, (b, c) in tqdm(anns.items(), desc=f"lifting PANDORA {self.split}",
                                 disable=not self.progress, leave=False):
            path = Path(self.root) / "images" / name
            img = decode_image(path, cv2.IMREAD_COLOR) if path.is_file() else None
            if img is None:
                raise FileNotFoundError(f"{path} is missing or not an image. " + GET_IT.format(
                    root=self.root, split=self.split))
            h, w = img.shape[:2]
            if w != 2 * h:
                raise ValueError(f"{path} is {w} x {h}; PANDORA panoramas are equirectangular, "
                                 f"twice as wide as high (1920 x 960)")
            if fe is None or fe.camera.width != w:
                fe = SphericalFrontend(Equirectangular(w, h), self.grid, interpolation=self.interpolation)
            xs.append(fe.lift(img[..., ::-1].astype(np.float32) / 255))
            boxes.append(b)
            classes.append(c)
        x = torch.stack(xs)
        if self.pre_transform is not None:
            x = pre_transform_stacked(self.pre_transform, (self._sample(xi, i) for i, xi in enumerate(x)),
                                      "x", fixed=("pos",))
        atomic_torch_save({"x": x.to(torch.float16), **pack_boxes(boxes, classes)}, self.processed_paths[0])

    def len(self) -> int:
        return len(self.x)

    def _sample(self, x, idx) -> SphericalImage:
        return SphericalImage(x=x, pos=self.grid.pos.float(), area=self.grid.area.float())

    def get(self, idx: int) -> SphericalImage:
        return add_boxes(self._sample(self.x[idx].float(), idx), self, idx)
