"""The camera interface and the numerics shared by the lens models.

Conventions (see DESIGN.md): rays are in the OpenCV optical frame (x right, y down,
z forward); ``rotation`` maps the optical frame to the sphere frame (x forward, y left,
z up). Pixels follow OpenCV: the centre of pixel (row i, column j) is (u, v) = (j, i).
All math is numpy float64. Invalid outputs are NaN and flagged False in ``valid``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..geometry import as_rotation_matrix
from .kept import kept_rays
from .resize import moved, resized, whole_pixels

FORMAT_TAG = "usf_graph_camera"  # marks usf-graph's own calibration YAML

# Optical axis -> +x, image right -> -y, image down -> -z (columns are the camera axes).
DEFAULT_ROTATION = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def plain(value) -> str:
    """A number as people write it (``-330.0``, not ``np.float64(-330.0)``)."""
    try:
        return repr(float(value))
    except (TypeError, ValueError):
        return repr(value)


def check_positive(name: str, value, fix: str = "") -> float:
    v = float(value)
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {plain(value)}. {fix}".strip())
    return v


def check_finite(name: str, values) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf: {arr.tolist()}. Check the calibration.")
    return arr


def set_intrinsics(cam, fx, fy, cx, cy) -> None:
    """``cam.fx, fy`` (positive) and ``cam.cx, cy`` (finite), checked, in pixels."""
    fix = "Focal lengths are in pixels and must be > 0."
    cam.fx, cam.fy = check_positive("fx", fx, fix), check_positive("fy", fy, fix)
    cam.cx, cam.cy = check_finite("cx", cx).item(), check_finite("cy", cy).item()


def check_rotation(R) -> np.ndarray:
    R = as_rotation_matrix(check_finite("rotation", R if R is not None else DEFAULT_ROTATION),
                           "rotation")
    # Re-orthonormalize so tiny file round-off does not accumulate.
    u, _, vt = np.linalg.svd(R)
    return u @ vt


def angle_to(rays: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Angle between each ray ``[..., 3]`` and ``axis [3]``, via atan2 (any norm)."""
    # |rays x axis| by components: the same numbers as np.cross and np.linalg.norm, 5x faster
    # on a whole image's rays (no temporary [..., 3] arrays to move about)
    rays = np.asarray(rays, np.float64)
    x, y, z = rays[..., 0], rays[..., 1], rays[..., 2]
    a, b, c = (float(v) for v in np.asarray(axis, np.float64))
    cx, cy, cz = y * c - z * b, z * a - x * c, x * b - y * a
    return np.arctan2(np.sqrt(cx * cx + cy * cy + cz * cz), rays @ axis)


def mask_from_image(m) -> np.ndarray:
    """``[H, W]`` or ``[H, W, C]`` image -> ``[H, W]`` bool: True where any channel is nonzero."""
    m = np.asarray(m)
    return (m if m.ndim == 2 else m.max(-1)) != 0


class Camera:
    """Base class: a calibrated camera that maps pixels to rays and back.

    Subclasses implement ``_project(rays) -> (uv, valid)`` and ``_unproject(uv) ->
    (rays, valid)`` on finite float64 arrays, and ``params()``.
    """

    model: str = "camera"
    wraps_u: bool = False  # True when the image is periodic in u (full panoramas)

    def __init__(self, width: int, height: int, rotation=None):
        self.width, self.height = whole_pixels("width", width), whole_pixels("height", height)
        self.rotation = check_rotation(rotation)
        self.fov_limit: float | None = None  # usable half-angle (rad) about the optical axis
        self.image_mask: np.ndarray | None = None  # [H, W] bool, False on pixels to ignore
        self.position: np.ndarray | None = None  # optical centre in the sphere frame
        self.distance: float | None = None  # radius of the scene sphere (None: at infinity)

    # -- to implement ------------------------------------------------------------
    def _project(self, rays: np.ndarray):
        raise NotImplementedError

    def _unproject(self, uv: np.ndarray):
        raise NotImplementedError

    def params(self) -> dict:
        """The model's parameters as keyword arguments of its constructor (the rotation and
        position apart): what :func:`~usf_graph.cameras.save` writes and the cache key hashes.
        """
        raise NotImplementedError

    optical_axis = np.array([0.0, 0.0, 1.0])

    # -- public ------------------------------------------------------------------
    def project(self, rays):
        """Rays ``[..., 3]`` (optical frame, any norm) -> pixels ``[..., 2]`` and ``valid``.

        ``valid`` is False outside the lens model's domain; image bounds are separate
        (see :meth:`in_image`).
        """
        rays = _as_last(rays, 3, "rays")
        finite = np.all(np.isfinite(rays), -1) & (np.linalg.norm(rays, axis=-1) > 0)
        rays = np.where(finite[..., None], rays, np.array([0.0, 0.0, 1.0]))
        uv, valid = self._project(rays)
        valid = valid & finite & np.all(np.isfinite(uv), -1) & self._within_fov(rays)
        return np.where(valid[..., None], uv, np.nan), valid

    def unproject(self, uv):
        """Pixels ``[..., 2]`` -> unit rays ``[..., 3]`` in the optical frame, and ``valid``."""
        uv = _as_last(uv, 2, "uv")
        finite = np.all(np.isfinite(uv), -1)
        uv = np.where(finite[..., None], uv, 0.0)
        rays, valid = self._unproject(uv)
        valid = valid & finite & np.all(np.isfinite(rays), -1)
        valid &= self._within_fov(np.where(valid[..., None], rays, self.optical_axis))
        return np.where(valid[..., None], rays, np.nan), valid

    def _within_fov(self, rays) -> np.ndarray:
        if self.fov_limit is None:
            return np.ones(rays.shape[:-1], bool)
        return angle_to(rays, self.optical_axis) <= self.fov_limit * (1 + 1e-12)

    def in_image(self, uv) -> np.ndarray:
        """True where a pixel coordinate lies on the sensor (pixel centres at integers)."""
        uv = np.asarray(uv, np.float64)
        u, v = uv[..., 0], uv[..., 1]
        ok_v = (v >= -0.5) & (v <= self.height - 0.5)
        ok_u = np.isfinite(u) if self.wraps_u else (u >= -0.5) & (u <= self.width - 0.5)
        return ok_u & ok_v

    def sample_positions(self, u, v):
        """Where to sample the image for points at pixel coordinates ``(u, v)``: within half
        a pixel of the image's border, the border pixel; a full panorama wraps in u. A
        camera whose image holds several regions (a cube map's faces) keeps each point
        within its own."""
        v = np.clip(v, 0, self.height - 1)
        u = np.mod(u, self.width) if self.wraps_u else np.clip(u, 0, self.width - 1)
        return u, v

    def pixels_with_rays(self) -> np.ndarray:
        """``[H, W]`` bool: the pixels that have a ray (in the lens model's domain and the
        usable field of view); the :attr:`image_mask` is not applied."""
        return self.pixel_rays()[1]

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`unproject` of every pixel centre: rays ``[H, W, 3]`` (optical frame) and
        ``valid [H, W]``, computed once per lens (:mod:`~usf_graph.cameras.kept`); a camera
        may compute it faster from its structure."""
        return kept_rays(json.dumps(self.lens_key(), sort_keys=True),
                         lambda: self.unproject(self.pixel_grid()))

    def pixel_grid(self) -> np.ndarray:
        """Pixel centres ``[H, W, 2]`` as (u, v)."""
        v, u = np.meshgrid(np.arange(self.height, dtype=np.float64),
                           np.arange(self.width, dtype=np.float64), indexing="ij")
        return np.stack([u, v], -1)

    def lens_normal_map(self):
        """Per-pixel unit rays in the sphere frame ``[H, W, 3]`` and ``valid [H, W]``
        (False also where :attr:`image_mask` is)."""
        rays, valid = self.pixel_rays()
        if self.image_mask is not None:
            valid = valid & self.image_mask
            rays = np.where(valid[..., None], rays, np.nan)
        rays = rays @ self.rotation.T
        if self.has_parallax:
            # where the ray from the optical centre t meets the scene sphere |p| = r:
            # |t + s w|^2 = r^2 with s > 0 (one root, since |t| < r)
            t, r = self.position, self.distance
            b = rays @ t
            s = -b + np.sqrt(b * b - t @ t + r * r)
            rays = (t + s[..., None] * rays) / r
        return rays, valid

    @property
    def has_parallax(self) -> bool:
        """True when the camera sits off the sphere's centre (:attr:`position`) and sees a
        scene at a finite :attr:`distance`, so that its rays are not the sphere's directions."""
        return self.distance is not None and self.position is not None and bool(self.position.any())

    def to_optical(self, points) -> np.ndarray:
        """Sphere-frame directions ``[..., 3]`` -> the rays ``[..., 3]`` (optical frame) along
        which this camera sees them: turned by :attr:`rotation`, and with parallax the ray
        to the scene point ``distance * p / |p|`` from the camera's :attr:`position`."""
        points = np.asarray(points, np.float64)
        if self.has_parallax:
            norm = np.linalg.norm(points, axis=-1, keepdims=True)
            points = self.distance * points / np.where(norm > 0, norm, np.nan) - self.position
        return points @ self.rotation

    def sees(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Sphere-frame points ``[..., 3]`` -> (pixels, seen): the camera's field-of-view test,
        with the :attr:`image_mask` (nearest pixel) when there is one."""
        uv, valid = self.project(self.to_optical(points))
        seen = valid & self.in_image(np.where(valid[..., None], uv, -1e9))
        if self.image_mask is not None:
            j = np.clip(np.rint(np.nan_to_num(uv[..., 0])), 0, self.width - 1).astype(np.int64)
            i = np.clip(np.rint(np.nan_to_num(uv[..., 1])), 0, self.height - 1).astype(np.int64)
            seen &= self.image_mask[i, j % self.width]
        return uv, seen

    @property
    def max_incidence(self) -> float:
        """Largest angle (radians) between a visible ray and the optical axis (pixels the
        :attr:`image_mask` ignores do not count)."""
        rays, valid = self.pixel_rays()
        if self.image_mask is not None:
            valid &= self.image_mask
        if not valid.any():
            return 0.0
        return float(np.max(angle_to(rays[valid], self.optical_axis)))

    @property
    def fov_deg(self) -> float:
        """Field of view in degrees: twice the maximum incidence angle."""
        return math.degrees(2 * self.max_incidence)

    def pixel_solid_angles(self) -> np.ndarray:
        """Solid angle (sr) each pixel covers ``[H, W]``; 0 where a pixel corner is invalid
        or the :attr:`image_mask` ignores the pixel.

        Each pixel is split into two spherical triangles between its corner rays.
        """
        v, u = np.meshgrid(np.arange(self.height + 1) - 0.5, np.arange(self.width + 1) - 0.5,
                           indexing="ij")
        c, ok = self.unproject(np.stack([u, v], -1))
        a, b, cc, d = c[:-1, :-1], c[:-1, 1:], c[1:, 1:], c[1:, :-1]
        okp = ok[:-1, :-1] & ok[:-1, 1:] & ok[1:, 1:] & ok[1:, :-1]
        om = _triangle_solid_angle(a, b, cc) + _triangle_solid_angle(a, cc, d)
        if self.image_mask is not None:
            okp &= self.image_mask
        return np.where(okp, om, 0.0)

    def solid_angle(self) -> float:
        """Total solid angle (sr) the image covers; 4*pi for a full panorama."""
        return float(self.pixel_solid_angles().sum())

    def _rebuild(self, rotation) -> Camera:
        return type(self)(**self.params(), rotation=rotation)

    def _copy(self, rotation=None, fov_limit=..., image_mask=..., position=...,
              distance=...) -> Camera:
        new = self._rebuild(self.rotation if rotation is None else rotation)
        new.fov_limit = self.fov_limit if fov_limit is ... else fov_limit
        new.image_mask = self.image_mask if image_mask is ... else image_mask
        new.position = self.position if position is ... else position
        new.distance = self.distance if distance is ... else distance
        if new.distance is not None and new.position is not None:
            far = float(np.linalg.norm(new.position))
            if far >= new.distance:
                raise ValueError(
                    f"the camera's optical centre is {plain(round(far, 9))} from the sphere's "
                    f"centre, outside the scene sphere of radius {plain(new.distance)}; give a "
                    "distance beyond every camera of the rig, in the unit of its positions")
        return new

    def with_rotation(self, rotation) -> Camera:
        """A copy of this camera mounted with another ``rotation`` (sphere <- camera); its
        :attr:`position` stays."""
        return self._copy(rotation=rotation)

    def turned(self, R) -> Camera:
        """A copy whose whole mounting is turned by ``R [3, 3]`` (the sphere frame's): its
        rotation becomes ``R @ rotation`` and its position ``R @ position``, so that it
        sees the scene turned by ``R`` exactly, with parallax too."""
        R = np.asarray(R, np.float64)  # the new rotation is checked where it is built
        new = self._copy(rotation=R @ self.rotation)
        return new if self.position is None else new.with_position(R @ self.position)

    def with_position(self, position) -> Camera:
        """A copy whose optical centre sits at ``position [3]`` in the sphere frame (a rig's
        cameras, in the unit of its calibration, e.g. metres); ``None``: at the centre. The
        position matters only with a :attr:`distance` (:meth:`with_distance`)."""
        if position is None:
            return self._copy(position=None)
        t = check_finite("position", np.asarray(position, np.float64))
        if t.shape != (3,):
            raise ValueError(f"position must be 3 numbers (x, y, z in the sphere frame), got "
                             f"shape {t.shape}")
        return self._copy(position=t)

    def with_distance(self, distance: float | None) -> Camera:
        """A copy that sees the scene as a sphere of radius ``distance`` about the sphere
        frame's centre (in the unit of :attr:`position`), so that a camera off the centre
        looks at each direction with parallax: the stitching distance of a rig whose
        cameras are apart. ``None``: the scene is at infinity and positions do not matter."""
        if distance is None:
            return self._copy(distance=None)
        return self._copy(distance=check_positive(
            "distance", distance, "It is the radius of the scene sphere, in the unit of the "
            "cameras' positions."))

    def resized(self, width: int, height: int) -> Camera:
        """This camera for its images resized to ``width x height`` by ``cv2.resize`` (the
        whole frame): the same lens on another pixel grid (:mod:`usf_graph.cameras.resize`)."""
        return resized(self, width, height)

    def _resized(self, width: int, height: int, sx: float, sy: float) -> Camera:
        # the models whose pixels are an affine map (fx, fy, cx, cy[, skew]) of a projection
        p = dict(self.params(), width=width, height=height)
        if "fx" not in p:
            raise ValueError(f"{type(self).__name__} cannot be resized")
        p.update(fx=self.fx * sx, fy=self.fy * sy, cx=float(moved(self.cx, sx)),
                 cy=float(moved(self.cy, sy)))
        if "skew" in p:
            p["skew"] = self.skew * sx
        return type(self)(**p, rotation=self.rotation)

    def with_fov(self, fov_deg: float | None) -> Camera:
        """A copy that sees only rays within ``fov_deg / 2`` of the optical axis (``None``:
        the whole lens). Use it for a lens whose calibration extrapolates past its image
        circle: a 190-degree fisheye calibrated as Kannala-Brandt may report 270."""
        if fov_deg is None:
            return self._copy(fov_limit=None)
        fov = check_positive("fov_deg", fov_deg, "It is the full field of view in degrees.")
        if fov > 360:
            raise ValueError(f"fov_deg must be at most 360 degrees, got {plain(fov_deg)}")
        return self._copy(fov_limit=math.radians(fov) / 2)

    def with_image_mask(self, mask, combine: bool = False) -> Camera:
        """A copy that ignores the pixels where ``mask [H, W]`` is False (vignetting, the
        robot's body); ``None`` removes the mask. ``combine``: it also keeps ignoring the
        pixels its current mask ignores."""
        if mask is None:
            return self._copy(image_mask=None)
        m = np.asarray(mask)
        if m.shape[:2] != (self.height, self.width) or m.ndim not in (2, 3):
            raise ValueError(f"image mask has shape {m.shape} but the camera's image is "
                             f"{self.height} x {self.width} (rows x columns)")
        m = mask_from_image(m)
        if combine and self.image_mask is not None:
            m = m & self.image_mask
        if not m.any():
            raise ValueError("the image mask is all zero: the camera would see nothing")
        return self._copy(image_mask=m)

    def lens_key(self) -> dict:
        """What the optical-frame rays (:meth:`pixel_rays`) depend on: the model, its
        parameters and its field-of-view limit, not where the camera is mounted."""
        k = {"model": self.model, "params": _jsonable(self.params())}
        if self.fov_limit is not None:
            k["fov_deg"] = round(math.degrees(2 * self.fov_limit), 12)
        return k

    def key(self) -> dict:
        """Everything that determines this camera's geometry (for cache keys and files)."""
        k = {**self.lens_key(), "rotation": np.round(self.rotation, 15).tolist()}
        if self.distance is not None:  # without one the position changes no ray
            k["distance"] = self.distance
            if self.position is not None:
                k["position"] = np.round(self.position, 12).tolist()
        if self.image_mask is not None:
            import hashlib

            k["image_mask"] = hashlib.sha256(np.packbits(self.image_mask).tobytes()).hexdigest()[:16]
        return k

    def to_doc(self) -> dict:
        """This camera as plain data (``usf_graph.cameras.from_doc`` reads it back); an
        image mask is not included, only its digest in :meth:`key`."""
        key = self.key()
        doc = {FORMAT_TAG: 1, "model": type(self).__name__, "rotation": key["rotation"],
               "params": key["params"]}
        for name in ("fov_deg", "distance"):
            if name in key:
                doc[name] = key[name]
        if self.position is not None:
            doc["position"] = np.round(self.position, 12).tolist()
        return doc

    def save(self, path) -> None:
        """Write this camera to ``path`` in usf-graph's YAML form (see ``cameras.load``),
        atomically. An image mask goes next to it as ``<stem>.mask.png``."""
        import yaml

        from ..fileio import atomic_write, write_image

        path = Path(path)
        doc = self.to_doc()
        if self.image_mask is not None:
            name = f"{path.stem}.mask.png"
            write_image(path.with_name(name), self.image_mask.astype(np.uint8) * 255)
            doc["image_mask"] = name
        text = yaml.safe_dump(doc, sort_keys=False)
        atomic_write(path, lambda f: f.write(text), "w")

    def __repr__(self) -> str:
        p = ", ".join(f"{k}={_short(v)}" for k, v in self.params().items())
        fov = "" if self.fov_limit is None else f".with_fov({plain(round(math.degrees(2 * self.fov_limit), 9))})"
        mask = "" if self.image_mask is None else f".with_image_mask(<{self.height}x{self.width} mask>)"
        pos = "" if self.position is None else f".with_position({_short(self.position)})"
        dist = "" if self.distance is None else f".with_distance({plain(self.distance)})"
        return f"{type(self).__name__}({p}){fov}{mask}{pos}{dist}"


def _triangle_solid_angle(a, b, c):
    # Van Oosterom & Strackee: tan(omega/2) = |a.(b x c)| / (1 + a.b + b.c + c.a) for unit vectors
    num = np.abs(np.einsum("...i,...i->...", a, np.cross(b, c)))
    den = 1 + (a * b).sum(-1) + (b * c).sum(-1) + (c * a).sum(-1)
    return 2 * np.arctan2(num, den)


def _as_last(x, n: int, name: str) -> np.ndarray:
    try:
        import torch

        if isinstance(x, torch.Tensor):
            x = x.detach().cpu().numpy()
    except ImportError:  # pragma: no cover
        pass
    x = np.asarray(x, dtype=np.float64)
    if x.shape[-1:] != (n,):
        raise ValueError(f"{name} must have shape [..., {n}], got {x.shape}")
    return x


def _jsonable(v):
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    if isinstance(v, (np.ndarray, np.generic, list, tuple)):
        return np.asarray(v).tolist()
    return v


def _short(v):
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, (list, tuple, np.ndarray)) and np.size(v) > 8:
        return f"<{np.shape(v)}>"
    return repr(_jsonable(v))
