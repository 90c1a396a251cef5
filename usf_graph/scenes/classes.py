"""Label spaces of the procedural rooms: Stanford 2D-3D-S's 13 classes for segmentation and a
subset of PANDORA's 47 for detection."""

from __future__ import annotations

import difflib

import numpy as np

#: Stanford 2D-3D-S's classes, alphabetical: the index is the label in ``View.label``.
SEMANTIC_CLASSES = ("beam", "board", "bookcase", "ceiling", "chair", "clutter", "column", "door",
                    "floor", "sofa", "table", "wall", "window")
#: Label of pixels without a ray (outside the lens), as the ignore index of losses.
IGNORE = 255

#: PANDORA's 47 categories in id order (ids 1..47).
PANDORA_CLASSES = (
    "airconditioner", "backpack", "bathtub", "bed", "board", "book", "bottle", "bowl", "bucket",
    "cabinet", "chair", "clock", "clothes", "computer", "cup", "cushion", "door", "extinguisher",
    "fan", "faucet", "fireplace", "heater", "keyboard", "light", "microwave", "mirror", "mouse",
    "outlet", "oven", "paper extraction", "person", "phone", "picture", "potted plant",
    "refrigerator", "shoes", "shower head", "sink", "sofa", "table", "toilet", "towel", "tv",
    "vase", "washer", "window", "wine glass")

#: The objects of the rooms that get boxes, named as in PANDORA; the index is the detection
#: label, :data:`PANDORA_IDS` the category id in PANDORA's files.
DETECTION_CLASSES = ("bed", "board", "book", "cabinet", "chair", "cup", "door", "light",
                     "picture", "sofa", "table", "window")
PANDORA_IDS = tuple(PANDORA_CLASSES.index(n) + 1 for n in DETECTION_CLASSES)

#: Colours of :data:`SEMANTIC_CLASSES` (RGB uint8) for figures; ignored pixels are black.
PALETTE = np.array([
    [176, 122, 64], [40, 160, 120], [132, 72, 180], [170, 200, 235], [230, 160, 30],
    [120, 120, 120], [90, 60, 40], [200, 60, 60], [150, 180, 80], [230, 90, 170],
    [250, 230, 70], [225, 225, 210], [60, 140, 230]], np.uint8)


def _index(name: str, names: tuple, what: str) -> int:
    if name in names:
        return names.index(name)
    close = difflib.get_close_matches(str(name), names, n=3)
    hint = f" Did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
    raise ValueError(f"unknown {what} class {name!r}.{hint} The classes are: {', '.join(names)}")


def semantic_index(name: str) -> int:
    """Index of a Stanford 2D-3D-S class name (``'chair'`` -> 4); unknown names raise."""
    return _index(name, SEMANTIC_CLASSES, "semantic")


def detection_index(name: str) -> int:
    """Index of a detection class name in :data:`DETECTION_CLASSES`; unknown names raise."""
    return _index(name, DETECTION_CLASSES, "detection")


def colourize(label: np.ndarray) -> np.ndarray:
    """Labels ``[H, W]`` -> RGB ``[H, W, 3]`` in :data:`PALETTE` (ignored pixels black)."""
    label = np.asarray(label)
    out = np.zeros(label.shape + (3,), np.uint8)
    ok = label < len(PALETTE)
    out[ok] = PALETTE[label[ok]]
    return out
