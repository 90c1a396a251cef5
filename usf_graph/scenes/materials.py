"""What a room's surfaces look like: a texture, a tint, how much of the texture shows
(``mix``) and its scale (``tile``, metres per repeat), per object.

Two kinds of rooms:

- ``"random"`` (the protocols' rooms): every object draws its look at random, whatever it
  is, so a class shows only in its shape and in the room around it;
- ``"by_kind"``: each kind of object draws its look from a material of its own (floors
  brownish carpet or stone, ceilings and walls pale paint, doors and tables wood, pictures
  photographs, windows bright sky, ...), as in real indoor scenes. Clutter (cups, bottles,
  books, boxes) keeps a random look. The room's layout and light are the same as its
  ``"random"`` twin's.
"""

from __future__ import annotations

import numpy as np

from .classes import SEMANTIC_CLASSES
from .textures import TEXTURES, num_textures

#: The kinds of rooms: :func:`appearance`'s ``materials``.
MATERIALS = ("random", "by_kind")

#: ``kind: (textures, tint, tint spread, mix range, tile range)``; structure goes by its
#: class (floor, ceiling, wall). Tints are RGB in [0, 1], drawn uniformly within the spread.
BY_KIND = {
    "floor": (("gravel", "moon"), (0.55, 0.42, 0.30), 0.12, (0.5, 0.9), (0.5, 1.5)),
    "ceiling": (("moon",), (0.92, 0.92, 0.90), 0.05, (0.1, 0.25), (1.0, 2.5)),
    "wall": (("moon", "brick"), (0.85, 0.82, 0.74), 0.10, (0.15, 0.4), (1.0, 2.5)),
    "column": (("moon",), (0.80, 0.80, 0.78), 0.10, (0.15, 0.4), (1.0, 2.5)),
    "beam": (("moon",), (0.80, 0.80, 0.80), 0.10, (0.15, 0.4), (1.0, 2.5)),
    "door": (("coffee", "coins"), (0.55, 0.35, 0.20), 0.10, (0.4, 0.8), (0.4, 1.0)),
    "window": (("hubble_deep_field",), (0.75, 0.88, 1.0), 0.08, (0.2, 0.5), (0.5, 1.5)),
    "board": (("page", "text"), (0.95, 0.95, 0.95), 0.04, (0.2, 0.5), (0.5, 1.5)),
    "picture": (("astronaut", "chelsea", "camera", "rocket"), (0.9, 0.9, 0.9), 0.1, (0.8, 1.0),
                (0.4, 1.0)),
    "table": (("coffee", "gravel"), (0.60, 0.40, 0.22), 0.12, (0.4, 0.8), (0.4, 1.2)),
    "chair": (("retina", "immunohistochemistry"), (0.35, 0.35, 0.55), 0.2, (0.3, 0.7), (0.4, 1.0)),
    "sofa": (("grass", "immunohistochemistry"), (0.55, 0.30, 0.30), 0.2, (0.4, 0.8), (0.4, 1.0)),
    "bed": (("coins", "moon"), (0.85, 0.85, 0.90), 0.1, (0.3, 0.6), (0.4, 1.0)),
    "bookcase": (("text", "brick"), (0.50, 0.35, 0.25), 0.12, (0.5, 0.9), (0.3, 0.8)),
    "cabinet": (("coffee", "coins"), (0.60, 0.55, 0.50), 0.15, (0.3, 0.7), (0.4, 1.0)),
    "floor_lamp": (("moon",), (0.98, 0.95, 0.80), 0.05, (0.1, 0.3), (0.4, 1.0)),
    "ceiling_light": (("moon",), (1.0, 0.98, 0.88), 0.03, (0.05, 0.2), (0.4, 1.0)),
}


def check_materials(materials: str) -> str:
    if materials not in MATERIALS:
        raise ValueError(f"materials must be one of {', '.join(MATERIALS)}, got {materials!r}")
    return materials


def material_key(kind: str, semantic: int) -> str:
    """The :data:`BY_KIND` entry of an object: its kind, or its class for structure."""
    return SEMANTIC_CLASSES[semantic] if kind == "structure" else kind


def appearance(instances, rng: np.random.Generator, materials: str = "random",
               seed=(0, 0)) -> dict:
    """Per-object ``texture``, ``tint``, ``mix``, ``tile``, ``offset`` arrays for a room's
    ``instances``. The random look is always drawn from ``rng`` (so what the room draws
    after it is the same for both kinds); ``"by_kind"`` then redraws the look of every
    object with a material from its own generator, seeded by ``seed`` (the room's seed and
    index)."""
    n = len(instances)
    ap = {"texture": rng.integers(0, num_textures(), n), "tint": rng.uniform(0.25, 1.0, (n, 3)),
          "mix": rng.uniform(0.3, 1.0, n), "tile": rng.uniform(0.4, 2.5, n),
          "offset": rng.uniform(0, 1, (n, 2))}
    if check_materials(materials) == "random":
        return ap
    own = np.random.default_rng([*seed, 7])
    for i, inst in enumerate(instances):
        mat = BY_KIND.get(material_key(inst.kind, inst.semantic))
        if mat is None:
            continue  # clutter
        tex, tint, spread, mix, tile = mat
        ap["texture"][i] = TEXTURES.index(tex[int(own.integers(len(tex)))])
        ap["tint"][i] = np.clip(np.asarray(tint) + own.uniform(-spread, spread, 3), 0.05, 1.0)
        ap["mix"][i] = own.uniform(*mix)
        ap["tile"][i] = own.uniform(*tile)
    return ap
