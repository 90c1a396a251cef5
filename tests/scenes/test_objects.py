"""The object builders keep their frame's promises: on the floor (or the wall), centred,
in one piece, at the heights of real furniture."""

import numpy as np
import pytest
from scipy.sparse.csgraph import connected_components

from usf_graph.scenes.classes import DETECTION_CLASSES, SEMANTIC_CLASSES
from usf_graph.scenes.objects import AGAINST_WALL, FLOOR, ON_TABLE, ON_WALL

#: (lowest, highest) top of each kind in metres, from its builder's ranges.
HEIGHTS = {"table": (0.70, 0.78), "chair": (0.83, 0.97), "sofa": (0.8, 0.9), "bed": (1.0, 1.1),
           "bookcase": (1.6, 2.2), "cabinet": (0.8, 1.2), "floor_lamp": (1.625, 1.925),
           "floor_clutter": (0.2, 0.5), "cup": (0.08, 0.12), "bottle": (0.2, 0.3),
           "book": (0.02, 0.06), "door": (2.06, 2.21), "window": (1.6, 2.4), "board": (1.6, 2.2),
           "picture": (1.55, 2.2)}
#: Kinds whose footprint is off-centre in y: a headboard behind the bed, a handle in front.
OFF_CENTRE_Y = ("bed", "cabinet")


def _bounds(parts):
    lo = np.array([p.bounds[0] for p in parts])
    hi = np.array([p.bounds[1] for p in parts])
    return lo, hi


def _one_piece(lo, hi) -> bool:
    """Whether the parts' boxes, touching or overlapping, join into one piece."""
    touch = (np.minimum(hi[:, None], hi[None]) - np.maximum(lo[:, None], lo[None]) >= -1e-9).all(-1)
    return connected_components(touch, directed=False)[0] == 1


def _span_their_heights(kind, tops) -> None:
    """The tops lie within the kind's HEIGHTS and reach into both ends' quarters."""
    lo, hi = HEIGHTS[kind]
    assert lo - 1e-9 <= min(tops) < lo + (hi - lo) / 4 and hi - (hi - lo) / 4 < max(tops) <= hi + 1e-9


def _builds(template, n=60):
    return [template.build(np.random.default_rng(seed)) for seed in range(n)]


@pytest.mark.parametrize("kind", [*FLOOR, *ON_TABLE])
def test_standing_objects_are_one_centred_piece_on_their_floor(kind):
    template = {**FLOOR, **ON_TABLE}[kind]
    tops = []
    for parts in _builds(template):
        lo, hi = _bounds(parts)
        low, high = lo.min(0), hi.max(0)
        assert abs(low[2]) < 1e-12 and _one_piece(lo, hi)
        assert abs(low[0] + high[0]) < 1e-9
        if kind not in OFF_CENTRE_Y:
            assert abs(low[1] + high[1]) < 1e-9
        # what touches the floor is centred under it (four legs, not two on one side)
        feet = np.vstack([p.vertices[abs(p.vertices[:, 2]) < 1e-12] for p in parts])
        centre = feet.min(0)[:2] + feet.max(0)[:2]
        assert abs(centre[0]) < 1e-9 and (kind in OFF_CENTRE_Y or abs(centre[1]) < 1e-9)
        tops.append(high[2])
    _span_their_heights(kind, tops)


@pytest.mark.parametrize("kind", ["chair", "sofa", "bed"])
def test_a_seat_or_bed_has_its_back_towards_plus_y(kind):
    """+y is the wall it stands against: the back (the highest part) is there."""
    for parts in _builds(FLOOR[kind], 10):
        lo, hi = _bounds(parts)
        back = np.argmax(hi[:, 2])
        assert abs(hi[back, 1] - hi[:, 1].max()) < 1e-9 and (lo[back, 1] + hi[back, 1]) / 2 > 0
        assert hi[back, 2] > np.delete(hi[:, 2], back).max() + 0.15  # it rises above the seat


@pytest.mark.parametrize("kind", ON_WALL)
def test_wall_items_hang_on_the_wall_in_one_piece(kind):
    tops = []
    for parts in _builds(ON_WALL[kind]):
        lo, hi = _bounds(parts)
        assert np.all(abs(hi[:, 1]) < 1e-12), "every part touches the wall (y = 0)"
        assert (lo[:, 1] < 0).all() and _one_piece(lo, hi)
        assert abs(lo[:, 0].min() + hi[:, 0].max()) < 1e-9 and lo[:, 2].min() >= -1e-12
        if kind == "door":
            assert abs(lo[:, 2].min()) < 1e-12  # it reaches the floor
        else:
            assert lo[:, 2].min() > 0.5
        tops.append(hi[:, 2].max())
    _span_their_heights(kind, tops)


def test_templates_name_real_classes():
    for table in (FLOOR, ON_TABLE, ON_WALL):
        for kind, t in table.items():
            assert t.kind == kind and t.semantic in SEMANTIC_CLASSES
            assert t.detect is None or t.detect in DETECTION_CLASSES
    assert set(AGAINST_WALL) <= set(FLOOR)
    detected = {t.detect for table in (FLOOR, ON_TABLE, ON_WALL) for t in table.values()}
    assert detected - {None} == set(DETECTION_CLASSES)  # every detection class has a builder
