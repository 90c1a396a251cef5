"""Straight lines of an image: the Manhattan axes they meet at, on exact great circles (any
frame), on rendered rooms through level, tilted and distorted pinholes, fisheyes and
panoramas, their frame turning with the camera; and up from them, which levels a tilted
panorama."""

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.helpers import FIXTURES
from usf_graph.cameras import Equirectangular, KannalaBrandt, Pinhole
from usf_graph.frontend import render as reimage
from usf_graph.frontend.lines import (
    LINE_TOLERANCE,
    MAX_TILT,
    LineFinder,
    UpTracker,
    _inner,
    image_up,
    line_normals,
    lines_up,
    manhattan_axes,
)
from usf_graph.geometry import level_rotation, rotation_from_axis_angle
from usf_graph.scenes import make_room, render
from usf_graph.scenes.lenses import protocol_cameras


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


#: The protocols' 190-degree Kannala-Brandt fisheye, at 128 pixels.
FISHEYE = protocol_cameras(128)["fisheye190"]


@pytest.mark.parametrize("tilt", [False, True])
@pytest.mark.parametrize("camera", [Equirectangular(256, 128), FISHEYE], ids=["panorama", "fisheye"])
def test_one_axis_is_up_through_lenses_that_bend_lines(camera, tilt):
    """A panorama's or a fisheye's lines are curves; re-imaged through a cube of pinholes
    they are straight again, and the room's axes come out as through a pinhole."""
    rgb, up = _room_view(camera, tilt)
    n, w = line_normals(rgb, camera)
    axes = manhattan_axes(n, w)
    assert len(n) > 50  # lines of several faces of the cube
    # (a 128-pixel fisheye: 1.0 degrees; the pinhole's test allows 2.5)
    assert np.degrees(np.arccos(min(1.0, np.abs(axes @ up).max()))) < 1.5


def test_lines_through_a_lens_that_bends_them_turn_with_the_camera():
    """The cube's faces stay in the sphere frame, so the turned camera's lines are found on
    other faces: the same room's axes, turned, not the same segments. Over six rooms,
    because one view's axes can be a few degrees off (room 3's are 3.4 degrees off, its
    turned view's 0.5; room 4 has too few lines for either)."""
    Q = rotation_from_axis_angle(np.array([1.0, 2.0, 2.0]) / 3, 0.7)
    errors = []
    for index in range(6):
        rgb, _ = _room_view(FISHEYE, tilt=False, index=index)
        axes = manhattan_axes(*line_normals(rgb, FISHEYE))
        axes2 = manhattan_axes(*line_normals(rgb, FISHEYE.with_rotation(Q @ FISHEYE.rotation)))
        errors.append(_frame_error(axes2, Q @ axes.T))
    errors = np.array(errors)
    assert (errors < 1.5).sum() >= 4 and np.median(errors) < 1.0, errors  # within about a degree


def test_image_up_is_where_the_image_points_up_at_its_centre():
    assert np.allclose(image_up(Equirectangular(64, 32)), [0, 0, 1], atol=1e-12)
    cam = Pinhole(64.0, 64.0, 63.5, 63.5, 128, 128)
    assert np.allclose(image_up(cam), [0, 0, 1], atol=1e-12)
    pitch = rotation_from_axis_angle(np.array([0.0, 1.0, 0.0]), math.radians(30))  # nose down
    assert np.allclose(image_up(cam.with_rotation(pitch @ cam.rotation)), pitch[:, 2], atol=1e-12)


@pytest.mark.parametrize("camera", [Equirectangular(256, 128), FISHEYE,
                                    Pinhole(64.0, 64.0, 63.5, 63.5, 128, 128)],
                         ids=["panorama", "fisheye", "pinhole"])
def test_lines_up_finds_gravity_through_a_tilt(camera):
    """Pitched by 25 and rolled by 10 degrees: the axis nearest the image's up, signed
    towards it, is gravity's up, within 1.5 degrees."""
    rgb, up = _room_view(camera, tilt=True)
    u = lines_up(rgb, camera)
    assert np.degrees(np.arccos(min(1.0, u @ up))) < 1.5  # the sign too


def test_leveling_a_tilted_panorama_gives_the_level_one():
    """Look, don't trust: the tilted panorama's camera mounted turned by
    level_rotation(lines_up(...)), re-imaged, matches the room rendered level along the same
    heading."""
    cam = Equirectangular(256, 128)
    scene = make_room(seed=3, index=3, materials="by_kind")
    pos, R0 = scene.viewpoint(0)
    T = rotation_from_axis_angle(np.array([0.0, 1.0, 0.0]), math.radians(15)) \
        @ rotation_from_axis_angle(np.array([1.0, 0.0, 0.0]), math.radians(-8))
    tilted = render(scene, cam, pos, R0 @ T, boxes=False).rgb.astype(np.float64)
    R = level_rotation(lines_up(tilted.astype(np.uint8), cam))
    leveled = reimage(tilted, cam.turned(R), cam)
    # the same as keeping the source and turning the target back
    assert np.allclose(reimage(tilted, cam, cam.turned(R.T)), leveled, atol=1e-9)
    # the room seen level along the heading the minimal turn keeps
    truth = render(scene, cam, pos, R0 @ T @ level_rotation(T.T @ [0.0, 0.0, 1.0]).T, boxes=False).rgb
    err = np.abs(leveled - truth).mean(-1)
    assert np.median(err) < 2.0 and err.mean() < 4.0  # two resamplings, a 0.3-degree error
    assert np.abs(tilted - truth).mean() > 12.0  # and the tilt was there to remove
    # the level room's verticals (door frames, shelves) are columns: the lines' up is +z
    assert np.degrees(np.arccos(lines_up(leveled.round().astype(np.uint8), cam)[2])) < 1.0


def test_lines_up_says_when_it_cannot_tell():
    cam = Equirectangular(256, 128)
    with pytest.raises(ValueError, match="too few"):
        lines_up(np.full((128, 256, 3), 90, np.uint8), cam)
    rgb, up = _room_view(cam, tilt=True)  # 27 degrees off: beyond a tolerance of 20
    with pytest.raises(ValueError, match="is a guess"):
        lines_up(rgb, cam, max_tilt=20.0)
    # a prior halfway between two axes is as near one as the other: refused (MAX_TILT < 45)
    axes = manhattan_axes(*line_normals(rgb, cam))
    k = int(np.abs(axes @ up).argmax())
    with pytest.raises(ValueError, match=f"over {MAX_TILT:g}"):
        lines_up(rgb, cam, prior=axes[k] + axes[(k + 1) % 3])
    with pytest.raises(ValueError, match="finite, non-zero"):
        lines_up(rgb, cam, prior=[0.0, 0.0, 0.0])


def test_line_normals_turn_with_the_camera():
    cam = Pinhole(64.0, 64.0, 63.5, 63.5, 128, 128)
    rgb, _ = _room_view(cam, tilt=False)
    n, w = line_normals(rgb, cam)
    Q = rotation_from_axis_angle(np.array([1.0, 2.0, 2.0]) / 3, 0.7)
    n2, w2 = line_normals(rgb, cam.with_rotation(Q @ cam.rotation))
    assert len(n) > 20 and np.allclose(n2, n @ Q.T, atol=1e-12) and np.allclose(w2, w)
    # float images in [0, 1] and 16-bit ones read as the same picture
    n3, _ = line_normals(rgb.astype(np.float64) / 255, cam)
    assert np.allclose(n3, n, atol=1e-12)
    n4, _ = line_normals(rgb.astype(np.uint16) * 257, cam)
    assert np.allclose(n4, n, atol=1e-12)


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


def _tilting_video(cameras, frames: int = 6):
    """A room filmed by ``cameras`` (one, or a rig's list) turning 10 degrees a frame while it
    tilts by 4 + 3k degrees about an axis that turns by a radian a frame, so that up moves by
    3 to 17 degrees from one frame to the next: each frame's images and its up."""
    scene = make_room(seed=3, index=3, materials="by_kind")
    pos, R0 = scene.viewpoint(0)
    out = []
    for k in range(frames):
        T = rotation_from_axis_angle(np.array([0.0, 0.0, 1.0]), math.radians(10 * k)) \
            @ rotation_from_axis_angle(np.array([math.cos(k), math.sin(k), 0.0]), math.radians(4 + 3 * k))
        ims = [render(scene, c, pos, R0 @ T, boxes=False).rgb for c in cameras]
        out.append((ims, T.T @ np.array([0.0, 0.0, 1.0])))
    return out


def test_a_line_finder_built_once_finds_what_a_fresh_one_finds():
    """The straight views built once serve every frame: on two different frames of a
    panorama and of a fisheye, the same segments as line_normals', which builds anew."""
    for cam in (Equirectangular(256, 128), FISHEYE):
        finder = LineFinder(cam)
        for ims, _ in _tilting_video([cam], 2):
            n, w = finder(ims[0])
            n0, w0 = line_normals(ims[0], cam)
            assert len(n) > 50 and np.array_equal(n, n0) and np.array_equal(w, w0)


def test_up_tracker_follows_a_tilting_camera_through_a_video():
    """Each frame's up within 1.5 degrees, also where up jumps out of the search window
    (the axis found in it has few of up's lines: the whole search again); a blank frame
    keeps the last up and is counted."""
    cam = Equirectangular(256, 128)
    video = _tilting_video([cam])
    ups = [u for _, u in video]
    moves = [math.degrees(np.arccos(np.clip(a @ b, -1, 1))) for a, b in zip(ups, ups[1:])]
    assert max(moves) > 12 and min(moves) < 8  # both kinds of step
    track = UpTracker(cam)
    for k, (ims, up) in enumerate(video):
        if k == 3:
            before = track.up.copy()
            assert np.array_equal(track(np.full((128, 256, 3), 90, np.uint8)), before)
            assert track.missed == 1
        got = track(ims[0])
        assert np.degrees(np.arccos(min(1.0, got @ up))) < 1.5, k
    assert track.frames == 7 and track.missed == 1
    with pytest.raises(ValueError, match="one image per camera"):
        UpTracker([cam, cam])([video[0][0][0]])


def test_up_tracker_reads_a_rigs_cameras_together():
    """Two back-to-back fisheyes: their lines, read together in the rig's frame, give up
    through the video, as one camera's do."""
    from usf_graph.cameras import load_rig

    rig = {n: c.with_fov(190).resized(128, 128) for n, c in
           load_rig(FIXTURES / "kalibr_rig.yaml").items()}
    track = UpTracker(rig)
    for ims, up in _tilting_video([c.with_position(None) for c in rig.values()], 3):
        assert np.degrees(np.arccos(min(1.0, track(ims) @ up))) < 1.5
    assert track.missed == 0


def test_image_up_of_a_fisheye_and_of_a_camera_blind_at_its_centre():
    """A distorted fisheye's up at its centre pixel is, by symmetry, its image's -y exactly
    (a pixel off it is not); and a camera with no ray at its image centre has no up."""
    fish = KannalaBrandt(30.0, 30.0, 63.5, 63.5, 128, 128, k=(0.05, 0.01, 0.0, 0.0))
    roll = rotation_from_axis_angle(np.array([1.0, 0.0, 0.0]), math.radians(20))
    for R in (np.eye(3), roll):
        cam = fish.with_rotation(R @ fish.rotation)
        assert np.allclose(image_up(cam), R[:, 2], atol=1e-12)
    blind = KannalaBrandt(30.0, 30.0, -300.0, 63.5, 128, 128, k=(0.0, 0.0, 0.0, 0.0)).with_fov(120)
    with pytest.raises(ValueError, match="no ray at its image centre"):
        image_up(blind)


def test_colour_images_are_read_as_the_mean_of_red_green_and_blue():
    cam = Pinhole(64.0, 64.0, 63.5, 63.5, 128, 128)
    rgb, _ = _room_view(cam, tilt=False)
    n, w = line_normals(rgb, cam)
    n2, w2 = line_normals(np.round(rgb.astype(np.float64).mean(-1)).astype(np.uint8), cam)
    assert len(n) > 20 and np.array_equal(n, n2) and np.array_equal(w, w2)
    blue = np.zeros((128, 128, 4), np.uint8)  # RGBA: alpha is no colour
    blue[:, 64:, 2] = 255
    blue[..., 3] = 255
    assert len(line_normals(blue, cam)[0]) >= 1


@pytest.mark.parametrize("upsample", [1, 2, 3])
def test_segments_are_placed_to_a_tenth_of_a_pixel_whatever_the_upsampling(upsample):
    """A bright rectangle whose sides lie halfway between pixels (x = 40.5, y = 30.5):
    back in the image's pixels, each side's great circle crosses the centre row or column
    there (OpenCV's LSD is off by about 0.05 pixel), enlarged or not."""
    cam = Pinhole(64.0, 64.0, 63.5, 63.5, 128, 128)
    img = np.zeros((128, 128), np.uint8)
    img[31:100, 41:110] = 200
    n, _ = line_normals(img, cam, upsample=upsample)
    n = n @ cam.rotation  # the camera's frame: a plane n . (x - cx, y - cy, f) = 0
    for side, (x, y, axis) in {"left": (40.5, None, 0), "top": (None, 30.5, 1)}.items():
        pick = np.abs(n[:, axis]) > 0.9 * np.linalg.norm(n[:, :2], axis=1)
        at = 63.5 - 64.0 * n[pick, 2] / n[pick, axis]
        want = x if axis == 0 else y
        assert np.abs(at - want).min() < 0.1, (side, at)


def test_a_segment_across_an_unseen_strip_is_left_out():
    """Its ends lie where the camera sees, its middle where it does not (a mast across the
    view): no line is read there."""
    cam = Pinhole(64.0, 64.0, 63.5, 63.5, 128, 128)
    img = np.zeros((128, 128), np.uint8)
    img[60:] = 200  # one horizontal edge across the image, at y = 59.5
    mask = np.ones((128, 128), bool)
    mask[:, 58:70] = False
    assert len(line_normals(img, cam)[0]) >= 1
    assert len(line_normals(img, cam.with_image_mask(mask))[0]) == 0


def test_where_segments_may_lie_is_two_pixels_from_anything_unseen():
    """Against a brute-force search: a pixel is inner where every pixel of the image within
    two rows and columns of it is seen."""
    seen = np.random.default_rng(0).random((30, 40)) > 0.03
    got = _inner(seen)
    want = np.zeros_like(seen)
    for i in range(30):
        for j in range(40):
            want[i, j] = seen[max(i - 2, 0):i + 3, max(j - 2, 0):j + 3].all()
    assert 0 < want.sum() < want.size and np.array_equal(got, want)


def test_a_direction_or_prior_of_any_length_means_its_direction():
    rng = np.random.default_rng(5)
    R = rotation_from_axis_angle(np.array([0.0, 0.6, 0.8]), 0.4)
    normals = np.concatenate([_circles_through(R[:, k], 12, rng) for k in range(3)])
    weights = rng.uniform(0.01, 0.05, len(normals))
    ref = manhattan_axes(normals, weights, near=R[:, 2], within=10.0)
    for scale in (0.05, 7.0):
        got = manhattan_axes(normals, weights, near=scale * R[:, 2], within=10.0)
        assert got is not None and np.allclose(got, ref, atol=1e-12)
    blank = np.full((128, 128), 90, np.uint8)  # no lines: the tracker keeps its prior
    up = UpTracker(Pinhole(64.0, 64.0, 63.5, 63.5, 128, 128), prior=[0.0, 0.0, 5.0])(blank)
    assert np.allclose(up, [0.0, 0.0, 1.0], atol=1e-15)
