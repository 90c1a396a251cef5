"""Straight lines of an image as great circles on the sphere, the three orthogonal
directions they meet at (a room's Manhattan axes), and the one of them that is up: a
geometric cue to up that needs no training, and holds through a narrow camera, where a
learned estimate sees little of the room.

A straight 3D line images to a straight segment through a pinhole without distortion;
its two ends' rays span a plane through the centre, whose normal ``n`` is orthogonal to
the line's direction. Parallel lines share a direction ``v`` (their vanishing direction)
with ``n . v = 0`` for each. OpenCV's line segment detector finds the segments (a camera
that bends lines is first re-imaged through pinholes); the axes are the directions that
the most line length points at. Everything is in the camera's sphere frame
(``camera.rotation`` applied), so the axes turn with the camera.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from ..cameras import Camera, Pinhole, cube_faces
from ..geometry import geodesic_distance
from .image import to_uint8
from .interpolation import valid_pixels
from .reimage import Reimager
from .remap import round_to

#: Lines closer than this (degrees) to a direction's great circle point at it.
LINE_TOLERANCE = 1.5
#: Fewer lines than this give no axes: a few segments fit any frame.
MIN_LINES = 8
#: The longest lines whose pairs are tried as the first axis (every pair: deterministic).
MAX_LINES = 200
#: Pixels: the largest side of the cube faces a lens that bends lines is re-imaged through
#: (0.18 degrees a pixel).
MAX_FACE = 512
#: Degrees: the most :func:`lines_up` lets up lie from its prior (at 45, two axes are as near).
MAX_TILT = 40.0


def _undistorted(camera: Camera):
    """``camera`` as a pinhole without distortion (the same intrinsics, size and mounting),
    or ``None`` when it is no pinhole."""
    if not isinstance(camera, Pinhole):
        return None
    p = camera.params()
    return Pinhole(p["fx"], p["fy"], p["cx"], p["cy"], p["width"], p["height"],
                   rotation=camera.rotation)


def _gray(image) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim == 3:
        a = a[..., :3] if a.shape[-1] >= 3 else a[..., 0]
    if a.ndim not in (2, 3):
        raise ValueError(f"image must be [H, W] or [H, W, C], got shape {np.asarray(image).shape}")
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        raise ValueError("the image has NaN or inf pixels; fill or mask them before finding lines")
    a = to_uint8(a)
    return a if a.ndim == 2 else np.round(a.mean(-1)).astype(np.uint8)


def _faces(camera: Camera) -> list[Pinhole]:
    """Six 90-degree pinholes without distortion, the faces of a cube about the sphere's
    centre (axes +-x, +-y, +-z of the sphere frame), each with about ``camera``'s angular
    pixel density at its image centre (at most :data:`MAX_FACE` pixels a side), and the
    faces that see none of ``camera``'s rays left out: the straight images of a camera that
    bends lines."""
    cy, cx = camera.height // 2, camera.width // 2
    px = np.array([[cx, cy], [cx + 1, cy], [cx, cy + 1]], np.float64)
    rays, valid = camera.unproject(px)
    step = [float(geodesic_distance(rays[0], rays[k])) for k in (1, 2)
            if valid[0] and valid[k] and px[k, 0] < camera.width and px[k, 1] < camera.height]
    if not step or min(step) <= 0:
        raise ValueError(f"{type(camera).__name__} has no rays at its image centre to tell its "
                         "resolution from; give a camera that sees there")
    # a face spans tan 45 = 1 each way; finer than MAX_FACE the lines gain little precision
    # and cost much time (a 4096-pixel panorama's faces would be 1,304 pixels a side)
    side = int(np.clip(math.ceil(2.0 / min(step)), 16, MAX_FACE))
    cube = cube_faces(side)
    return [cube[k] for k in ("front", "left", "back", "right", "up", "down")  # +x, +y, -x, -y, +z, -z
            if camera.sees(cube[k].lens_normal_map()[0].reshape(-1, 3))[1].any()]


def _inner(seen: np.ndarray) -> np.ndarray:
    """Where a segment of a straight image may lie: not within 2 pixels of a pixel the camera
    does not see (``seen [H, W]``; the image's own border is no such pixel)."""
    return cv2.erode(np.pad(seen, 1, mode="edge").astype(np.uint8), np.ones((5, 5), np.uint8))[1:-1, 1:-1] > 0


def _segment_normals(gray: np.ndarray, inner: np.ndarray, ideal: Pinhole,
                     upsample: int | None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`line_normals` of a straight image ``gray [H, W]`` (uint8) taken by the pinhole
    ``ideal`` (no distortion), with segments kept where ``inner [H, W]`` (:func:`_inner`)."""
    h, w = gray.shape
    up = (2 if max(h, w) < 512 else 1) if upsample is None else max(int(upsample), 1)
    found = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD).detect(
        cv2.resize(gray, None, fx=up, fy=up, interpolation=cv2.INTER_LINEAR))[0]
    if found is None:
        return np.zeros((0, 3)), np.zeros(0)
    seg = found.reshape(-1, 4).astype(np.float64) / up - (up - 1) / (2 * up)  # back to pixels
    ends = [seg[:, :2], seg[:, 2:], (seg[:, :2] + seg[:, 2:]) / 2]
    keep = np.ones(len(seg), bool)
    for p in ends:
        i = np.clip(np.round(p[:, 1]).astype(int), 0, h - 1)
        j = np.clip(np.round(p[:, 0]).astype(int), 0, w - 1)
        keep &= inner[i, j]
    a, va = ideal.unproject(seg[keep, :2])
    b, vb = ideal.unproject(seg[keep, 2:])
    ok = va & vb
    R = ideal.rotation
    n = np.cross(a[ok] @ R.T, b[ok] @ R.T)
    length = np.linalg.norm(n, axis=1)
    long = length > 1e-9
    return n[long] / length[long, None], np.arcsin(np.clip(length[long], 0, 1))


class LineFinder:
    """The straight segments of images that ``camera`` (any model) takes, as great circles:
    :func:`line_normals` for many images of one camera (a video's frames), with the straight
    views an image is read through and their re-imaging built once, here, not per image.

    A pinhole's image is read as it is (with distortion, re-imaged through the same pinhole
    without it first); any other camera's (a fisheye, a panorama), which bends straight
    lines, is re-imaged through the six faces of a cube of 90-degree pinholes
    (:func:`_faces`), and a line a face's border cuts counts as its two pieces, on one great
    circle. ``upsample``: each straight image is enlarged this many times first, so that
    short segments are found (OpenCV's LSD, default parameters); by default twice below 512
    pixels a side, else not.

    ``camera`` may be a rig's cameras (a sequence or a dict, mounted in the rig's frame):
    each call then takes one image per camera, in order, and gives their lines together,
    in the rig's sphere frame. Where lines point does not depend on where a camera sits, so
    each camera's lines are read from its own centre (a position the rig's stitching gave
    it is dropped)."""

    def __init__(self, camera, upsample: int | None = None):
        self.rig = not isinstance(camera, Camera)
        cams = list(camera.values() if isinstance(camera, dict) else camera) if self.rig else [camera]
        if not cams:
            raise ValueError("no cameras to find lines for: give a camera or a rig's cameras")
        self.cameras, self.upsample = [c.with_position(None) for c in cams], upsample
        self._views = []  # per camera: (its re-imaging or None, where segments may lie, view)
        for cam in self.cameras:
            seen, ideal = valid_pixels(cam), _undistorted(cam)
            if ideal is not None and not cam.params().get("dist"):
                self._views.append([(None, _inner(seen), ideal)])
                continue
            views = []
            for v in [ideal] if ideal is not None else _faces(cam):
                r = Reimager(cam, v, source_valid=seen)
                views.append((r, _inner(r.seen), v))
            self._views.append(views)

    def __call__(self, image) -> tuple[np.ndarray, np.ndarray]:
        """``normals [L, 3]`` (unit, sphere frame) of the great circles through the segments
        of ``image`` (``[H, W]`` or ``[H, W, C]``; uint8, uint16 or floats in [0, 1]; a rig:
        a list of one per camera), and ``weights [L]``: their angular lengths (radians).
        Segments that touch pixels the camera does not see are left out, so the border of
        its image mask is no line."""
        images = list(image) if self.rig else [image]
        if len(images) != len(self.cameras):
            raise ValueError(f"{len(images)} images for {len(self.cameras)} cameras: give one "
                             "image per camera, in order")
        found = []
        for im, cam, views in zip(images, self.cameras, self._views):
            if np.asarray(im).shape[:2] != (cam.height, cam.width):
                raise ValueError(f"the image is {np.asarray(im).shape[:2]} (H, W), the camera's "
                                 f"{(cam.height, cam.width)}: give the image the camera was "
                                 "calibrated for")
            gray = _gray(im)
            for r, inner, v in views:
                straight = gray if r is None else round_to(r(gray.astype(np.float32)), np.uint8)
                found.append(_segment_normals(straight, inner, v, self.upsample))
        return np.concatenate([n for n, _ in found]), np.concatenate([w for _, w in found])


def line_normals(image, camera: Camera, upsample: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The straight segments of ``image`` taken by ``camera``, as ``(normals [L, 3],
    weights [L])``: :class:`LineFinder` for one image (a 1080p image: about 1 s in all, on
    2 cores; for a video's frames, build one :class:`LineFinder` and call it on each)."""
    return LineFinder(camera, upsample)(image)


def rig_line_normals(images, cameras) -> tuple[np.ndarray, np.ndarray]:
    """:func:`line_normals` of a rig's ``cameras`` (mounted in the rig's frame) on their
    ``images`` (one each, in order), together, in the rig's sphere frame: a rig's
    :class:`LineFinder` for one set of images."""
    return LineFinder(list(cameras))(images)


def _support(v: np.ndarray, normals: np.ndarray, weights: np.ndarray, tol: float) -> np.ndarray:
    """The line length pointing at each direction of ``v [K, 3]``."""
    return ((np.abs(v @ normals.T) < math.sin(math.radians(tol))) * weights).sum(-1)


def _second_axis(v1: np.ndarray, normals: np.ndarray, weights: np.ndarray, tolerance: float):
    """The direction orthogonal to ``v1`` (half-degree steps) at which the most line length
    points, and that length."""
    e1 = np.cross(v1, np.eye(3)[np.abs(v1).argmin()])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(v1, e1)
    t = np.radians(np.arange(0.0, 180.0, 0.5))
    circle = np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2
    s = _support(circle, normals, weights, tolerance)
    return circle[s.argmax()], s.max()


def manhattan_axes(normals: np.ndarray, weights: np.ndarray, tolerance: float = LINE_TOLERANCE,
                   min_lines: int = MIN_LINES, max_lines: int = MAX_LINES,
                   tries: int = 20, near=None, within: float = 90.0) -> np.ndarray | None:
    """Three orthogonal unit directions ``[3, 3]`` (rows) at which the most line length
    points, from :func:`line_normals`' output, or ``None`` with fewer than ``min_lines``
    lines. A line points at a direction within ``tolerance`` degrees of its great circle.

    The intersections of every pair of the ``max_lines`` longest lines are the candidates
    for a first axis; each of the ``tries`` best (at least 5 degrees apart) gets the best
    second axis on the great circle orthogonal to it (half-degree steps) and the third
    that completes them, and the frame at which the most line length points in all wins.
    Not the best single direction alone: lines of a texture can meet anywhere. Each axis is
    then fitted to its lines (:func:`_refined`). Deterministic; each axis is defined up to
    sign. ``near`` (a direction ``[3]``) keeps only the first axes within ``within`` degrees
    of it (either sign): where one axis is known roughly (up, a frame earlier in a video),
    the search is that much shorter."""
    normals, weights = np.asarray(normals, np.float64), np.asarray(weights, np.float64)
    if normals.ndim != 2 or normals.shape[1:] != (3,) or weights.shape != normals.shape[:1]:
        raise ValueError(f"normals must be [L, 3] and weights [L], got {normals.shape} and "
                         f"{weights.shape}")
    if len(normals) < max(min_lines, 2):
        return None
    top = normals[np.argsort(-weights, kind="stable")[:max_lines]]
    i, j = np.triu_indices(len(top), 1)
    c = np.cross(top[i], top[j])
    norm = np.linalg.norm(c, axis=1)
    c = c[norm > 1e-6] / norm[norm > 1e-6, None]
    if near is not None:
        c = c[np.abs(c @ (np.asarray(near, np.float64) / np.linalg.norm(near)))
              >= math.cos(math.radians(within))]
    if not len(c):
        return None
    order = np.argsort(-_support(c, normals, weights, tolerance), kind="stable")
    firsts: list[np.ndarray] = []
    for k in order:  # the best candidates, 5 degrees apart (either sign)
        if all(abs(c[k] @ f) < math.cos(math.radians(5)) for f in firsts):
            firsts.append(c[k])
            if len(firsts) == tries:
                break
    best, frame = -1.0, None
    for v1 in firsts:
        v2, _ = _second_axis(v1, normals, weights, tolerance)
        axes = np.stack([v1, v2, np.cross(v1, v2)])
        total = float(_support(axes, normals, weights, tolerance).sum())
        if total > best:
            best, frame = total, axes
    return _refined(frame, normals, weights, tolerance)


def _refined(axes: np.ndarray, normals: np.ndarray, weights: np.ndarray, tolerance: float) -> np.ndarray:
    """Each axis fitted to the lines pointing at it (least squares: the direction most
    orthogonal to their normals, weighted), then the nearest orthogonal frame: the search
    places an axis only to within ``tolerance``, the lines do better."""
    fitted = []
    for u in axes:
        for tol in (tolerance, tolerance / 2):  # the second pass drops lines the first pulled by
            near = np.abs(normals @ u) < math.sin(math.radians(tol))
            if near.sum() >= 2:
                n = normals[near]
                v = np.linalg.eigh((weights[near, None] * n).T @ n)[1][:, 0]
                u = v if v @ u >= 0 else -v
        fitted.append(u)
    U, _, Vt = np.linalg.svd(np.stack(fitted))
    return U @ Vt


def image_axes(images, camera: Camera, **kw) -> list[np.ndarray | None]:
    """:func:`manhattan_axes` of each image of ``images`` (``[S, H, W(, C)]``) taken by
    ``camera``; ``kw`` go to :func:`manhattan_axes`."""
    return [manhattan_axes(*line_normals(im, camera), **kw) for im in images]


def image_up(camera: Camera) -> np.ndarray:
    """The direction ``[3]`` (sphere frame) in which ``camera``'s image points up at its
    centre: the tangent at the centre pixel's ray towards the ray one pixel above it. Up
    for a level camera; for a panorama, its +z."""
    c = np.array([[(camera.width - 1) / 2, (camera.height - 1) / 2]])
    rays, valid = camera.unproject(np.concatenate([c, c - [0.0, 1.0]]))
    if not valid.all():
        raise ValueError(f"{type(camera).__name__} has no ray at its image centre, so its image "
                         "has no up to start from: give the prior (a known up) instead")
    a, b = rays @ camera.rotation.T
    t = b - (b @ a) * a
    return t / np.linalg.norm(t)


def _image_up(finder: LineFinder) -> np.ndarray:
    """Where up is looked for by default: :func:`image_up` of one camera, a rig's +z."""
    return np.array([0.0, 0.0, 1.0]) if finder.rig else image_up(finder.cameras[0])


def _prior(prior) -> np.ndarray:
    p = np.asarray(prior, np.float64).reshape(3)
    if not (np.isfinite(p).all() and np.linalg.norm(p) > 0):
        raise ValueError(f"the prior up must be a finite, non-zero 3-vector, got {p.tolist()}")
    return p / np.linalg.norm(p)


def _axis_up(axes, count: int, prior: np.ndarray, max_tilt: float) -> np.ndarray:
    """Of the Manhattan ``axes`` (``None``: too few of ``count`` lines), the one nearest
    ``prior``, signed towards it; raises as :func:`lines_up` says."""
    if axes is None:
        raise ValueError(f"the image has {count} straight lines, too few (under {MIN_LINES}) "
                         "to tell up from: give up instead (an IMU, or a model's estimate)")
    k = int(np.abs(axes @ prior).argmax())
    up = axes[k] * np.sign(axes[k] @ prior)
    tilt = math.degrees(float(geodesic_distance(up, prior)))
    if tilt > max_tilt:
        raise ValueError(f"the lines' axis nearest the prior up lies {tilt:.1f} degrees from it "
                         f"(over {max_tilt:g}), so which axis is up is a guess: give a prior "
                         "nearer up, e.g. from an IMU")
    return up


def lines_up(image, camera, prior=None, max_tilt: float = MAX_TILT) -> np.ndarray:
    """Up ``[3]`` in ``camera``'s sphere frame from the straight lines of ``image``: of the
    Manhattan axes they meet at (:func:`line_normals`, :func:`manhattan_axes`), the one
    nearest ``prior`` (default :func:`image_up`: the camera held roughly upright), signed
    towards it. No training, and no reliance on what the room looks like: walls, doors,
    shelves and windows give the lines. For a video's frames, :class:`UpTracker`.

    ``camera`` may be a rig's cameras (a sequence or a dict, mounted in the rig's frame),
    with ``image`` a list of their images in order: their lines are read together
    (:class:`LineFinder`), up is in the rig's frame, and the default prior its +z.

    Raises where the image has too few straight lines, and where the nearest axis lies more
    than ``max_tilt`` degrees from ``prior``: past 45 degrees another axis is nearer, so
    which one is up is a guess (give a prior nearer up, e.g. from an IMU)."""
    finder = LineFinder(camera)
    p = _prior(_image_up(finder) if prior is None else prior)
    normals, weights = finder(image)
    return _axis_up(manhattan_axes(normals, weights), len(normals), p, max_tilt)


class UpTracker:
    """Up through a video, from each frame's straight lines: a horizon that holds while a
    handheld or vehicle camera tilts. Each frame's up is the Manhattan axis
    (:func:`manhattan_axes`) nearest the previous frame's up, searched within ``step``
    degrees of it; the first frame's is :func:`lines_up`'s, nearest ``prior``, and so is a
    frame's where the axis found near the last up has under half the share of the line
    length that up had (up moved out of the window). A frame with too few lines, or no axis
    within ``max_tilt`` of the last up, keeps the last up and counts in :attr:`missed`.

    Args:
        cameras: the camera (each frame one image), or a rig's cameras mounted in the rig's
            frame (each frame a list of images, one per camera, in order): their lines are
            read together, in the rig's sphere frame.
        prior: where the first frame's up is looked for (default: :func:`image_up` of a
            camera, the rig frame's +z for a rig).
        step: degrees up may move from one frame to the next.
        max_tilt: as :func:`lines_up`'s, for the first frame.

    The straight views the lines are read through are built once (:class:`LineFinder`),
    and the search near the last up is short: 0.12 s a frame for a 1024x512 panorama on 2
    cores, against 0.70 s for :func:`lines_up` (``benchmarks/lines.py --video``)."""

    def __init__(self, cameras, prior=None, step: float = 10.0, max_tilt: float = MAX_TILT):
        self._lines = LineFinder(cameras)
        self.up = _prior(_image_up(self._lines) if prior is None else prior)
        self.step, self.max_tilt = float(step), float(max_tilt)
        self.frames = self.missed = 0
        self._found, self._share = False, 0.0

    def __call__(self, images) -> np.ndarray:
        """Up ``[3]`` (unit, sphere frame) of the next frame: ``images``, one image, or a
        list of one per camera for a rig."""
        normals, weights = self._lines(images)
        self.frames += 1

        def found(near: bool) -> bool:
            window = {"near": self.up, "within": self.step} if near else {}
            try:
                up = _axis_up(manhattan_axes(normals, weights, **window), len(normals), self.up,
                              self.step if near else self.max_tilt)
            except ValueError:
                return False
            # the share of the line length pointing at up: where up left the window, what
            # was found in it has few of up's lines
            share = float(_support(up[None], normals, weights, LINE_TOLERANCE)[0]) / \
                max(float(weights.sum()), 1e-12)
            if near and share < self._share / 2:
                return False
            self.up, self._share = up, share
            return True

        # near the last frame's up where it was found, else (or failing that) everywhere
        self._found = (self._found and found(True)) or found(False)
        self.missed += not self._found
        return self.up.copy()


__all__ = ["LINE_TOLERANCE", "MIN_LINES", "MAX_LINES", "MAX_FACE", "MAX_TILT", "LineFinder", "UpTracker",
           "line_normals", "manhattan_axes", "image_axes", "image_up", "lines_up", "rig_line_normals"]
