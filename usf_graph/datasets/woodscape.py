r"""WoodScape (Yogamani et al., ICCV 2019): Valeo's four surround-view fisheyes on two
cars, with semantic labels, as a PyG dataset on the sphere.

Reads the released layout::

    root/rgb_images/<frame>_<FV|RV|MVL|MVR>.png          # 1280 x 966
    root/semantic_annotations/gtLabels/<frame>_<cam>.png  # one class index per pixel
    root/calibration_data/calibration/<frame>_<cam>.json  # or root/calibration/...
    root/train.txt, root/val.txt                          # OmniDet's lists, for split=

Every image has its own calibration (:mod:`usf_graph.cameras.woodscape`): its camera is
read from it, mounted in the vehicle frame (x forward, y left, z up), so all four cameras
lift into one frame with gravity along +z, each seeing its own part of the sphere. The 10
classes are OmniDet's: 0 void, then road, lanemarks, curb, person, rider, vehicles,
bicycle, motorcycle, traffic_sign; as in OmniDet a label past 9 counts as void. Points a
camera does not see get label 255 (ignored).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch_geometric.data import Dataset
from tqdm.auto import tqdm

from .. import cameras
from ..fileio import atomic_torch_save
from ..frontend import SphericalFrontend
from ..frontend.image import SphericalImage
from ..frontend.interpolation import choose_interpolation, valid_pixels
from ..grids import Grid, from_spec
from ..scenes import IGNORE
from .stacked import (
    UprightAsReleased,
    load_or_rebuild,
    missing_release,
    pre_transform_stacked,
    read_release_image,
)

CLASSES = ("void", "road", "lanemarks", "curb", "person", "rider", "vehicles", "bicycle",
           "motorcycle", "traffic_sign")
CAMERAS = ("FV", "RV", "MVL", "MVR")
GET_IT = ("WoodScape is distributed by Valeo (https://woodscape.valeo.com, and the links in "
          "https://github.com/valeoai/WoodScape): download the RGB images, the semantic "
          "annotations and the calibration, and unpack them so that {root}/rgb_images, "
          "{root}/semantic_annotations/gtLabels and {root}/calibration_data/calibration exist; "
          "for split='train' or 'val', copy OmniDet's omnidet/data/{{train,val}}.txt to {root}.")


def woodscape_images(root, split: str) -> list[str]:
    """The image names (``00020_FV``) of ``split``: ``train`` or ``val`` from ``root``'s
    list of that name (OmniDet's, one ``<name>.png`` a line), ``all`` every labelled image."""
    root = Path(root)
    labels = root / "semantic_annotations" / "gtLabels"
    if not labels.is_dir():
        raise FileNotFoundError(f"{labels} not found. " + GET_IT.format(root=root))
    if split == "all":
        names = sorted(p.stem for p in labels.glob("*.png"))
    else:
        listed = root / f"{split}.txt"
        if not listed.is_file():
            raise FileNotFoundError(f"{listed} not found: the split's image list. "
                                    + GET_IT.format(root=root))
        names = [Path(line.strip()).stem for line in listed.read_text().splitlines() if line.strip()]
    if not names:
        raise FileNotFoundError(f"no images in split {split!r} under {root}. " + GET_IT.format(root=root))
    return names


def _calibration(root: Path, name: str) -> Path:
    for folder in (root / "calibration_data" / "calibration", root / "calibration"):
        if (folder / f"{name}.json").is_file():
            return folder / f"{name}.json"
    raise FileNotFoundError(f"no calibration for {name} (calibration_data/calibration/{name}.json). "
                            + GET_IT.format(root=root))


class WoodScape(UprightAsReleased, Dataset):
    r"""WoodScape's fisheye images lifted to a spherical grid through each image's own
    calibration, with per-point labels (layout and classes in the module docstring).

    Args:
        root: the dataset folder; processed tensors go to ``root/processed``.
        split: ``train``, ``val`` (OmniDet's lists, copied to ``root``) or ``all``.
        grid: grid spec or :class:`~usf_graph.grids.Grid`.
        scale: images (and their calibrations, :meth:`~usf_graph.cameras.Camera.resized`)
            are resized by this factor first (area averaging for RGB, nearest for labels).

    A sample has ``x [N, 3]`` (RGB in [0, 1], 0 where unseen), ``y [N]`` (0..9, 255 where
    the camera does not see), ``mask [N]`` (its camera's field of view), ``pos``,
    ``area`` and its camera's name ``camera`` (FV, RV, MVL, MVR). The split in static form:
    ``dataset.x``, ``.y``, ``.mask``, ``.names``, ``.camera_names``, ``.calibrations`` (each
    sample's calibration file, relative to ``root``); ``dataset.gravity`` is +z (the
    vehicle frame's up, for ``usf-graph eval --known-up``). :meth:`frontend` and
    :meth:`label_image` give a sample's camera and its labels in that camera's pixels, for
    scoring on the images (:func:`usf_graph.train.real.run_woodscape`).
    """

    def __init__(self, root, split: str = "train", grid="icosahedral:5", scale: float = 0.5,
                 transform=None, pre_transform=None, progress: bool = True):
        if split not in ("train", "val", "all"):
            raise ValueError(f"split must be 'train', 'val' or 'all', got {split!r}")
        if not 0 < scale <= 1:
            raise ValueError(f"scale must be in (0, 1], got {scale}")
        self.split, self.scale, self.progress = split, float(scale), progress
        self._cache: dict = {}  # frontends by calibration content
        self._contents: dict = {}  # calibration content by path
        self.grid: Grid = from_spec(grid) if isinstance(grid, str) else grid
        super().__init__(str(root), transform, pre_transform, log=False)
        blob = load_or_rebuild(self.processed_paths[0], self.process,
                               ("x", "y", "mask", "names", "camera_names", "calibrations"))
        for k, v in blob.items():
            setattr(self, k, v)

    @property
    def raw_dir(self) -> str:
        """The release is read where it is: ``root`` itself."""
        return self.root

    @property
    def raw_file_names(self):
        return ["rgb_images", "semantic_annotations"]

    @property
    def processed_file_names(self):
        spec = self.grid.spec.replace(":", "").replace(",", "_")
        return [f"woodscape_{self.split}_{spec}_{self.scale:g}.pt"]

    def download(self):
        raise missing_release(self, GET_IT.format(root=self.root))

    def _frontends(self, calibration: Path) -> tuple:
        """The lifting and label frontends of a calibration file at this dataset's scale, and
        the release's image size; one per distinct calibration (the files repeat per camera)."""
        key = self._contents.get(calibration)
        if key is None:  # read once: a split's scoring asks for each sample's camera
            key = self._contents[calibration] = calibration.read_bytes()
        if key not in self._cache:
            cam = cameras.load(calibration)
            full = (cam.width, cam.height)
            size = (round(cam.width * self.scale), round(cam.height * self.scale))
            cam = cam.resized(*size) if size != full else cam
            self._cache[key] = (SphericalFrontend(cam, self.grid,
                                                  interpolation=choose_interpolation(cam, self.grid)),
                                SphericalFrontend(cam, self.grid, interpolation="nearest"), full)
        return self._cache[key]

    def _read(self, name: str, size: tuple, full: tuple, rgb: bool = True):
        """Image ``name``'s RGB (``None`` unless ``rgb``) and labels (void for any label past
        the classes, as OmniDet), checked against its calibration and resized to ``size``."""
        import cv2

        root, get_it = Path(self.root), GET_IT.format(root=self.root)
        label = read_release_image(root / "semantic_annotations" / "gtLabels" / f"{name}.png",
                                   cv2.IMREAD_GRAYSCALE, get_it)
        shapes = {"its calibration": full, "its label image": (label.shape[1], label.shape[0])}
        if rgb:
            rgb = read_release_image(root / "rgb_images" / f"{name}.png", cv2.IMREAD_COLOR,
                                     get_it)[..., ::-1]
            shapes["the image"] = (rgb.shape[1], rgb.shape[0])
        else:
            rgb = None
        if len(set(shapes.values())) > 1:
            raise ValueError(f"{name}: " + ", ".join(f"{k} is {w}x{h}" for k, (w, h) in shapes.items())
                             + "; they must match")
        label = np.where(label < len(CLASSES), label, 0).astype(np.uint8)
        if size != full:
            label = cv2.resize(label, size, interpolation=cv2.INTER_NEAREST)
            if rgb is not None:
                rgb = cv2.resize(np.ascontiguousarray(rgb), size, interpolation=cv2.INTER_AREA)
        return (rgb if rgb is None else np.ascontiguousarray(rgb)), label

    def process(self):
        root = Path(self.root)
        xs, ys, masks, names, cams, calibs = [], [], [], [], [], []
        for name in tqdm(woodscape_images(root, self.split), desc=f"lifting WoodScape {self.split}",
                         disable=not self.progress, leave=False):
            calib = _calibration(root, name)
            fe, labels_fe, full = self._frontends(calib)
            rgb, label = self._read(name, (fe.camera.width, fe.camera.height), full)
            xs.append(fe.lift(rgb.astype(np.float32) / 255))
            ys.append(labels_fe.lift(label)[:, 0].round().long().masked_fill(~fe.mask, IGNORE))
            masks.append(fe.mask)
            names.append(name)
            cams.append(name.rsplit("_", 1)[-1])
            calibs.append(calib.relative_to(root).as_posix())
        x, y, mask = torch.stack(xs), torch.stack(ys).to(torch.uint8), torch.stack(masks)
        if self.pre_transform is not None:
            x = pre_transform_stacked(self.pre_transform,
                                      (self._sample(x[i], y[i], mask[i]) for i in range(len(x))),
                                      "x", fixed=("pos",))
        atomic_torch_save({"x": x.to(torch.float16), "y": y, "mask": mask, "names": names,
                           "camera_names": cams, "calibrations": calibs}, self.processed_paths[0])

    def frontend(self, idx: int) -> SphericalFrontend:
        """Sample ``idx``'s camera (at the dataset's scale) and grid: its field of view is
        ``mask[idx]``, and :meth:`~usf_graph.frontend.SphericalFrontend.to_labels` renders
        per-point predictions into its pixels."""
        return self._frontends(Path(self.root) / self.calibrations[idx])[0]

    def label_image(self, idx: int) -> np.ndarray:
        """Sample ``idx``'s labels ``[H, W]`` (uint8) in its camera's pixels at the dataset's
        scale, read from the release: the classes 0..9, and 255 (ignored) on the pixels
        without a ray (past the image circle)."""
        fe, _, full = self._frontends(Path(self.root) / self.calibrations[idx])
        cam = fe.camera
        label = self._read(self.names[idx], (cam.width, cam.height), full, rgb=False)[1]
        return np.where(valid_pixels(cam), label, IGNORE).astype(np.uint8)

    def len(self) -> int:
        return len(self.x)

    def _sample(self, x, y, mask) -> SphericalImage:
        return SphericalImage(x=x.float(), y=y.long(), mask=mask.clone(), pos=self.grid.pos.float(),
                              area=self.grid.area.float())

    def get(self, idx: int) -> SphericalImage:
        d = self._sample(self.x[idx], self.y[idx], self.mask[idx])
        d.camera = self.camera_names[idx]
        return d

    def __repr__(self) -> str:
        return f"WoodScape({len(self)}, split={self.split}, grid={self.grid.spec}, scale={self.scale:g})"


__all__ = ["WoodScape", "CLASSES", "CAMERAS", "woodscape_images"]
