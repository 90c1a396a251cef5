"""Procedural indoor rooms seen through any camera, with exact labels, depth and boxes.

>>> from usf_graph import cameras, scenes
>>> scene = scenes.make_room(seed=0, index=3)
>>> view = scenes.render(scene, cameras.Equirectangular(512, 256))
>>> view.rgb.shape, view.label.shape, view.boxes.shape[1]
((256, 512, 3), (256, 512), 5)
"""

from .classes import (
                      DETECTION_CLASSES,
                      IGNORE,
                      PALETTE,
                      PANDORA_CLASSES,
                      PANDORA_IDS,
                      SEMANTIC_CLASSES,
                      colourize,
                      detection_index,
                      semantic_index,
)
from .render import View, render, world_boxes
from .room import Scene, make_room

__all__ = ["DETECTION_CLASSES", "IGNORE", "PALETTE", "PANDORA_CLASSES", "PANDORA_IDS",
           "SEMANTIC_CLASSES", "Scene", "View", "colourize", "detection_index", "make_room",
           "render", "semantic_index", "world_boxes"]
