"""Object meshes for the procedural rooms, built from trimesh boxes and cylinders.

Every builder takes a ``numpy.random.Generator`` and returns a list of ``trimesh.Trimesh``
parts in the object's own frame: the footprint centred on the origin (in y too, but for a
bed's headboard and a cabinet's handle), z up from the floor, the object's back towards +y
(the wall it stands against; a wall item's parts all touch the wall at y = 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh


@dataclass
class Template:
    """One kind of object: its Stanford class, its PANDORA detection name (or None), and
    its builder ``rng -> [trimesh.Trimesh, ...]``."""

    kind: str
    semantic: str
    detect: str | None
    build: object


def box(ext, centre) -> trimesh.Trimesh:
    """An axis-aligned box of extents ``ext`` centred on ``centre``."""
    m = trimesh.creation.box(extents=ext)
    m.apply_translation(centre)
    return m


def cylinder(radius, height, centre, sections: int = 16) -> trimesh.Trimesh:
    """A vertical cylinder centred on ``centre``."""
    m = trimesh.creation.cylinder(radius=radius, height=height, sections=sections)
    m.apply_translation(centre)
    return m


def _legs(hx, hy, h, t, inset):
    return [box((t, t, h), (sx * (hx - inset), sy * (hy - inset), h / 2))
            for sx in (-1, 1) for sy in (-1, 1)]


def table(rng):
    w, d, h = rng.uniform(0.8, 1.8), rng.uniform(0.6, 1.0), rng.uniform(0.70, 0.78)
    return [box((w, d, 0.04), (0, 0, h - 0.02))] + _legs(w / 2, d / 2, h - 0.04, 0.05, 0.06)


def chair(rng):
    s, h = rng.uniform(0.42, 0.5), rng.uniform(0.43, 0.47)
    back = rng.uniform(0.4, 0.5)
    return ([box((s, s, 0.04), (0, 0, h - 0.02)),
             box((s, 0.04, back), (0, s / 2 - 0.02, h + back / 2))]
            + _legs(s / 2, s / 2, h - 0.04, 0.035, 0.03))


def sofa(rng):
    w, d = rng.uniform(1.4, 2.2), rng.uniform(0.8, 0.95)
    top, arm = rng.uniform(0.8, 0.9), 0.15
    return [box((w, d, 0.42), (0, 0, 0.21)),
            box((w, 0.2, top - 0.42), (0, d / 2 - 0.1, (top + 0.42) / 2)),
            box((arm, d - 0.2, 0.18), (-(w - arm) / 2, -0.1, 0.51)),
            box((arm, d - 0.2, 0.18), ((w - arm) / 2, -0.1, 0.51))]


def bed(rng):
    w, length = rng.uniform(1.0, 1.8), rng.uniform(1.9, 2.1)
    head = rng.uniform(1.0, 1.1)
    return [box((w, length, 0.3), (0, 0, 0.15)),
            box((w - 0.06, length - 0.1, 0.2), (0, -0.03, 0.4)),
            box((w, 0.06, head), (0, length / 2 + 0.03, head / 2))]


def bookcase(rng):
    w, d, h = rng.uniform(0.6, 1.2), rng.uniform(0.3, 0.4), rng.uniform(1.6, 2.2)
    t = 0.025
    parts = [box((t, d, h), (sx * (w - t) / 2, 0, h / 2)) for sx in (-1, 1)]
    parts.append(box((w, t, h), (0, (d - t) / 2, h / 2)))
    n = int(rng.integers(3, 6))
    parts += [box((w - 2 * t, d - t, t), (0, -t / 2, z)) for z in np.linspace(t / 2, h - t / 2, n + 1)]
    return parts


def cabinet(rng):
    w, d, h = rng.uniform(0.5, 1.2), rng.uniform(0.4, 0.6), rng.uniform(0.8, 1.2)
    return [box((w, d, h), (0, 0, h / 2)), box((w * 0.3, 0.03, 0.03), (0, -d / 2 - 0.015, h * 0.8))]


def floor_lamp(rng):
    h, r = rng.uniform(1.4, 1.7), rng.uniform(0.18, 0.25)
    return [cylinder(0.15, 0.03, (0, 0, 0.015)), cylinder(0.015, h, (0, 0, h / 2)),
            cylinder(r, 0.25, (0, 0, h + 0.1))]


def bin_or_box(rng):
    if rng.random() < 0.5:
        r, h = rng.uniform(0.12, 0.2), rng.uniform(0.3, 0.5)
        return [cylinder(r, h, (0, 0, h / 2))]
    e = rng.uniform(0.2, 0.5, 3)
    return [box(e, (0, 0, e[2] / 2))]


def cup(rng):
    r, h = rng.uniform(0.035, 0.05), rng.uniform(0.08, 0.12)
    return [cylinder(r, h, (0, 0, h / 2), sections=12)]


def bottle(rng):
    r, h = rng.uniform(0.03, 0.045), rng.uniform(0.2, 0.3)
    return [cylinder(r, h, (0, 0, h / 2), sections=12)]


def book(rng):
    e = (rng.uniform(0.15, 0.22), rng.uniform(0.2, 0.28), rng.uniform(0.02, 0.06))
    return [box(e, (0, 0, e[2] / 2))]


# Wall items: x along the wall, +y into the wall, z from the floor; ``depth`` out of the wall.
def door(rng):
    w, h = rng.uniform(0.8, 1.1), rng.uniform(2.0, 2.15)
    f = 0.06
    return [box((w, 0.04, h), (0, -0.02, h / 2)), box((f, 0.06, h + f), (-(w + f) / 2, -0.03, (h + f) / 2)),
            box((f, 0.06, h + f), ((w + f) / 2, -0.03, (h + f) / 2)),
            box((w, 0.06, f), (0, -0.03, h + f / 2))]


def window(rng):
    w, h, sill = rng.uniform(0.8, 2.0), rng.uniform(0.8, 1.4), rng.uniform(0.8, 1.0)
    f = 0.05
    pane = box((w, 0.01, h), (0, -0.005, sill + h / 2))
    frame = [box((f, 0.05, h), (sx * (w - f) / 2, -0.025, sill + h / 2)) for sx in (-1, 1)]
    frame += [box((w, 0.05, f), (0, -0.025, sill + sz * (h - f) / 2 + h / 2)) for sz in (-1, 1)]
    return [pane] + frame


def board(rng):
    w, h, low = rng.uniform(1.0, 2.4), rng.uniform(0.8, 1.2), rng.uniform(0.8, 1.0)
    return [box((w, 0.02, h), (0, -0.01, low + h / 2)), box((w, 0.06, 0.03), (0, -0.03, low - 0.015))]


def picture(rng):
    w, h, mid = rng.uniform(0.3, 1.0), rng.uniform(0.3, 0.8), rng.uniform(1.4, 1.8)
    return [box((w, 0.03, h), (0, -0.015, mid))]


FLOOR = {t.kind: t for t in (
    Template("table", "table", "table", table), Template("chair", "chair", "chair", chair),
    Template("sofa", "sofa", "sofa", sofa), Template("bed", "clutter", "bed", bed),
    Template("bookcase", "bookcase", None, bookcase),
    Template("cabinet", "clutter", "cabinet", cabinet),
    Template("floor_lamp", "clutter", "light", floor_lamp),
    Template("floor_clutter", "clutter", None, bin_or_box))}
#: Objects against a wall, with their back touching it.
AGAINST_WALL = ("sofa", "bed", "bookcase", "cabinet")
ON_TABLE = {t.kind: t for t in (
    Template("cup", "clutter", "cup", cup), Template("bottle", "clutter", None, bottle),
    Template("book", "clutter", "book", book))}
ON_WALL = {t.kind: t for t in (
    Template("door", "door", "door", door), Template("window", "window", "window", window),
    Template("board", "board", "board", board), Template("picture", "clutter", "picture", picture))}
