"""Writing rendered views in the real datasets' on-disk formats.

- Labels as 8-bit PNGs of class indices (255 = ignore) and in the palette.
- Depth as 16-bit PNGs at 1/512 m with 65535 for "no data", as Stanford 2D-3D-S stores it.
- Boxes of panoramas as PANDORA's COCO-like JSON: ``bbox = [lon, lat, fov_x, fov_y, gamma]``
  in degrees in the image's terms, ``category_id`` in PANDORA's 47 categories.
- Whole releases (:func:`export_stanford`, :func:`export_pandora`): panoramas in the
  folder layouts the real datasets ship, so that their loaders and commands
  (``usf-graph train seg --dataset stanford2d3ds``, ``train det --dataset pandora``) run on
  procedural rooms where the real data cannot be had.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..cameras import Equirectangular
from ..fileio import atomic_write, write_image
from ..ops.boxes import to_pandora
from .classes import IGNORE, PANDORA_CLASSES, PANDORA_IDS, SEMANTIC_CLASSES, colourize
from .render import View

#: Stanford 2D-3D-S's areas, as its folders name them.
STANFORD_AREAS = ("1", "2", "3", "4", "5a", "5b", "6")
#: The colour of Stanford 2D-3D-S's pixels without data (an index past the label list's end).
STANFORD_MISSING = 0x0D0D0D


def depth_png(depth: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Depth in metres -> uint16 at 1/512 m, 65535 where there is no ray (Stanford's format)."""
    d = np.clip(np.round(depth.astype(np.float64) * 512), 0, 65534).astype(np.uint16)
    return np.where(valid, d, np.uint16(65535))


def save_view(view: View, out, stem: str) -> dict:
    """Write ``<stem>_rgb.png``, ``_label.png`` (class indices), ``_label_color.png`` and
    ``_depth.png`` under ``out``; returns their file names."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = {"rgb": f"{stem}_rgb.png", "label": f"{stem}_label.png",
             "label_color": f"{stem}_label_color.png", "depth": f"{stem}_depth.png"}
    write_image(out / files["rgb"], view.rgb[..., ::-1])
    write_image(out / files["label"], view.label)
    write_image(out / files["label_color"], colourize(view.label)[..., ::-1])
    write_image(out / files["depth"], depth_png(view.depth, view.valid))
    return files


def pandora_json(panoramas: list[tuple[str, View]], camera) -> dict:
    """PANDORA-style annotations of equirectangular views: ``[(file_name, view), ...]``."""
    _check_panorama(camera, "PANDORA boxes are defined on full equirectangular panoramas with "
                            "the identity rotation; render those to export boxes")
    images, anns = [], []
    for i, (name, view) in enumerate(panoramas, 1):
        images.append({"id": i, "file_name": name, "width": camera.width, "height": camera.height})
        for b, c in zip(to_pandora(view.boxes), view.box_class):
            anns.append({"id": len(anns) + 1, "image_id": i, "bbox": [round(float(v), 6) + 0.0 for v in b],
                         "category_id": int(PANDORA_IDS[c]), "area": 1, "iscrowd": 0})
    cats = [{"id": k + 1, "name": n} for k, n in enumerate(PANDORA_CLASSES)]
    return {"images": images, "annotations": anns, "categories": cats}


def stanford_entries() -> list[str]:
    """The ``semantic_labels.json`` of exported views: ``<UNK>``, then one entry per class,
    named as the release names instances (``<class>_<instance>_<room>_<n>``)."""
    return ["<UNK>"] + [f"{c}_1_procedural_1" for c in SEMANTIC_CLASSES]


def stanford_semantic(label: np.ndarray) -> np.ndarray:
    """Class indices ``[H, W]`` (255: ignored) -> the release's semantic image ``[H, W, 3]``
    (RGB uint8): per pixel the index ``R * 65536 + G * 256 + B`` into
    :func:`stanford_entries` (class k: entry k + 1), ignored pixels the missing-data colour."""
    label = np.asarray(label)
    idx = np.where(label == IGNORE, STANFORD_MISSING, label.astype(np.int64) + 1)
    return np.stack([idx >> 16, (idx >> 8) & 255, idx & 255], -1).astype(np.uint8)


def export_stanford(views: list[View], camera, root) -> list[Path]:
    """Write views through ``camera`` (a full upright equirectangular one) in Stanford
    2D-3D-S's layout under ``root``: view i in
    ``area_<STANFORD_AREAS[i % 7]>/pano/{rgb,semantic,depth}/camera_<i>_procedural_<i>_frame_
    equirectangular_domain_{rgb,semantic,depth}.png`` (semantic as :func:`stanford_semantic`,
    depth as :func:`depth_png`), and ``semantic_labels.json``. Returns the RGB paths."""
    _check_panorama(camera, _RELEASES)
    root, paths = Path(root), []
    for i, view in enumerate(views):
        pano = root / f"area_{STANFORD_AREAS[i % len(STANFORD_AREAS)]}" / "pano"
        stem = f"camera_{i:06d}_procedural_{i}_frame_equirectangular_domain"
        for kind, img in (("rgb", view.rgb[..., ::-1]), ("semantic", stanford_semantic(view.label)[..., ::-1]),
                          ("depth", depth_png(view.depth, view.valid))):
            (pano / kind).mkdir(parents=True, exist_ok=True)
            write_image(pano / kind / f"{stem}_{kind}.png", img)
        paths.append(pano / "rgb" / f"{stem}_rgb.png")
    doc = json.dumps(stanford_entries())
    atomic_write(root / "semantic_labels.json", lambda fh: fh.write(doc), "w")
    return paths


def export_pandora(views: list[View], camera, root, test_every: int = 5) -> dict[str, int]:
    """Write views through ``camera`` (a full upright equirectangular one) in PANDORA's
    layout under ``root``: ``images/<name>.jpg``
    and ``annotations/{train,test}.json`` (:func:`pandora_json`); every ``test_every``-th
    view is a test view. Returns the number of views per split."""
    import cv2

    _check_panorama(camera, _RELEASES)
    if test_every < 2:
        raise ValueError(f"test_every must be at least 2 (every test_every-th view a test one), got {test_every}")
    root = Path(root)
    (root / "images").mkdir(parents=True, exist_ok=True)
    splits: dict[str, list] = {"train": [], "test": []}
    for i, view in enumerate(views):
        name = f"procedural_{i:06d}.jpg"
        write_image(root / "images" / name, view.rgb[..., ::-1], (cv2.IMWRITE_JPEG_QUALITY, 95))
        splits["test" if i % test_every == test_every - 1 else "train"].append((name, view))
    for split, items in splits.items():
        doc = json.dumps(pandora_json(items, camera), indent=1)
        atomic_write(root / "annotations" / f"{split}.json", lambda fh, d=doc: fh.write(d), "w")
    return {k: len(v) for k, v in splits.items()}


_RELEASES = ("the releases hold full upright equirectangular panoramas; render the views "
             "through cameras.Equirectangular(2 H, H)")


def _check_panorama(camera, why: str) -> None:
    """A full equirectangular camera with the identity rotation, else ``ValueError(why)``."""
    if not isinstance(camera, Equirectangular) or not np.allclose(camera.rotation, np.eye(3)):
        raise ValueError(why)
