"""Writing rendered views in the real datasets' on-disk formats.

- Labels as 8-bit PNGs of class indices (255 = ignore) and in the palette.
- Depth as 16-bit PNGs at 1/512 m with 65535 for "no data", as Stanford 2D-3D-S stores it.
- Boxes of panoramas as PANDORA's COCO-like JSON: ``bbox = [lon, lat, fov_x, fov_y, gamma]``
  in degrees in the image's terms, ``category_id`` in PANDORA's 47 categories.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..cameras import Equirectangular
from ..fileio import atomic_write
from ..ops.boxes import to_pandora
from .classes import PANDORA_CLASSES, PANDORA_IDS, colourize
from .render import View


def _png(path: Path, img: np.ndarray) -> None:
    import cv2

    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise OSError(f"could not encode {path}")
    atomic_write(path, lambda f: f.write(buf.tobytes()))


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
    _png(out / files["rgb"], view.rgb[..., ::-1])
    _png(out / files["label"], view.label)
    _png(out / files["label_color"], colourize(view.label)[..., ::-1])
    _png(out / files["depth"], depth_png(view.depth, view.valid))
    return files


def pandora_json(panoramas: list[tuple[str, View]], camera) -> dict:
    """PANDORA-style annotations of equirectangular views: ``[(file_name, view), ...]``."""
    if not isinstance(camera, Equirectangular) or not np.allclose(camera.rotation, np.eye(3)):
        raise ValueError("PANDORA boxes are defined on full equirectangular panoramas with the "
                         "identity rotation; render those to export boxes")
    images, anns = [], []
    for i, (name, view) in enumerate(panoramas, 1):
        images.append({"id": i, "file_name": name, "width": camera.width, "height": camera.height})
        for b, c in zip(to_pandora(view.boxes), view.box_class):
            anns.append({"id": len(anns) + 1, "image_id": i, "bbox": [round(float(v), 6) + 0.0 for v in b],
                         "category_id": int(PANDORA_IDS[c]), "area": 1, "iscrowd": 0})
    cats = [{"id": k + 1, "name": n} for k, n in enumerate(PANDORA_CLASSES)]
    return {"images": images, "annotations": anns, "categories": cats}
