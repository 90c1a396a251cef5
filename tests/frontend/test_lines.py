"""Straight lines through a pinhole: the Manhattan axes they meet at, on exact great circles
(any frame), on rendered rooms through level, tilted and distorted pinholes, and their
frame turning with the camera."""

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from usf_graph.cameras import Equirectangular, Pinhole
from usf_graph.frontend.lines import LINE_TOLERANCE, line_normals, manhattan_axes
from usf_graph.geometry import rotation_from_axis_angle
from usf_graph.scenes import make_room, render


def _frame_error(axes: np.ndarray, R: np.ndarray) -> float:
    """Degrees: the worst of R's columns against the nearest of the axes, either sign."""
    cos = np.abs(axes @ R).max(0)
    return float(np.degrees(np.arccos(np.clip(cos.min(), 0, 1))))


def _circles_through(d: np.ndarray, n: int, rng) -> np.ndarray:
    """Normals of ``n`` random great circles through the direction ``d``."""
    v = rng.normal(size=(n, 3))
    v -= (v @ d)[:, None] * d
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_manhattan_axes_find_any_frame_among_clutter(seed):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    R = rotation_from_axis_angle(q[:3] / np.linalg.norm(q[:3]), math.pi * abs(np.tanh(q[3])))
    # 12 lines towards each axis, 3 of them long, and 15 lines of clutter pointing anywhere
    normals = np.concatenate([_circles_through(R[:, k], 12, rng) for k in range(3)]
                             + [rng.normal(size=(15, 3))])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    weights = rng.uniform(0.01, 0.05, len(normals))
    axes = manhattan_axes(normals, weights)
    assert np.allclose(axes @ axes.T, np.eye(3), atol=1e-9)
    # within the lines' tolerance: a line of another family (or of clutter) that passes
    # near an axis by chance pulls its fit (up to 0.93 degrees in 4,000 draws)
    assert _frame_error(axes, R) < LINE_TOLERANCE
    # the same lines in another order give the same frame: no random draws
    perm = rng.permutation(len(normals))
    assert np.allclose(np.abs(manhattan_axes(normals[perm], weights[perm]) @ axes.T).max(0), 1, atol=1e-9)


def test_manhattan_axes_need_enough_lines_and_say_what_they_read():
    rng = np.random.default_rng(0)
    n = _circles_through(np.array([0.0, 0.0, 1.0]), 7, rng)
    assert manhattan_axes(n, np.ones(7)) is None  # under MIN_LINES: no frame from a few lines
    with pytest.raises(ValueError, match=r"normals must be \[L, 3\]"):
        manhattan_axes(n[:, :2], np.ones(7))


def _room_view(camera, tilt: bool, index: int = 3):
    """An image of a room with materials by kind through ``camera``, and the up in its
    sphere frame: level at a random yaw, or pitched by 25 and rolled by 10 degrees."""
    scene = make_room(seed=3, index=index, materials="by_kind")
    pos, R = scene.viewpoint(0)
    if tilt:
        R = R @ rotation_from_axis_angle(np.array([0.0, 1.0, 0.0]), math.radians(25)) \
            @ rotation_from_axis_angle(np.array([1.0, 0.0, 0.0]), math.radians(10))
    return render(scene, camera, pos, R, boxes=False).rgb, R.T @ np.array([0.0, 0.0, 1.0])


@pytest.mark.parametrize("tilt", [False, True])
@pytest.mark.parametrize("dist", [None, [-0.25, 0.06, 0.0, 0.0]])
def test_one_axis_is_up_through_level_tilted_and_distorted_pinholes(tilt, dist):
    """Not a level-camera prior: the axes come from the room's lines wherever the camera
    points, and a distorted pinhole's image is straightened first."""
    cam = Pinhole(64.0, 64.0, 63.5, 63.5, 128, 128, dist=dist)
    rgb, up = _room_view(cam, tilt)
    axes = manhattan_axes(*line_normals(rgb, cam))
    err = np.degrees(np.arccos(min(1.0, np.abs(axes @ up).max())))
    assert err < 2.5


def test_line_normals_turn_with_the_camera():
    cam = Pinhole(64.0, 64.0, 63.5, 63.5, 128, 128)
    rgb, _ = _room_view(cam, tilt=False)
    n, w = line_normals(rgb, cam)
    Q = rotation_from_axis_angle(np.array([1.0, 2.0, 2.0]) / 3, 0.7)
    n2, w2 = line_normals(rgb, cam.with_rotation(Q @ cam.rotation))
    assert len(n) > 20 and np.allclose(n2, n @ Q.T, atol=1e-12) and np.allclose(w2, w)
    # float images in [0, 1] read as the same picture
    n3, _ = line_normals(rgb.astype(np.float64) / 255, cam)
    assert np.allclose(n3, n, atol=1e-12)


def test_lines_are_not_found_on_the_border_of_an_image_mask():
    """A camera's mask makes a hard edge in the image (black beyond it); it is no line."""
    cam = Pinhole(64.0, 64.0, 63.5, 63.5, 128, 128)
    rgb = np.full((128, 128, 3), 200, np.uint8)
    mask = np.zeros((128, 128), bool)
    mask[20:100, 30:110] = True
    rgb[~mask] = 0
    assert len(line_normals(rgb, cam)[0]) >= 4  # the unmasked camera sees the border as lines
    assert len(line_normals(rgb, cam.with_image_mask(mask))[0]) == 0


def test_line_normals_refuse_what_they_cannot_read():
    cam = Pinhole(64.0, 64.0, 63.5, 63.5, 128, 128)
    with pytest.raises(ValueError, match="perspective camera"):
        line_normals(np.zeros((64, 128, 3), np.uint8), Equirectangular(128, 64))
    with pytest.raises(ValueError, match="the camera's"):
        line_normals(np.zeros((64, 64, 3), np.uint8), cam)
    bad = np.zeros((128, 128, 3))
    bad[3, 4, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        line_normals(bad, cam)


def test_only_small_images_are_enlarged_before_the_search():
    rng = np.random.default_rng(0)
    for size, times in ((128, 2), (600, 1)):
        img = np.zeros((size, size), np.uint8)
        for _ in range(12):
            a, b = rng.integers(0, size, (2, 2))
            cv2.line(img, tuple(int(v) for v in a), tuple(int(v) for v in b), 255, 2)
        cam = Pinhole(size / 2, size / 2, (size - 1) / 2, (size - 1) / 2, size, size)
        n, w = line_normals(img, cam)
        n2, w2 = line_normals(img, cam, upsample=times)
        assert len(n) > 5 and np.array_equal(n, n2) and np.array_equal(w, w2)
