"""Cameras defined by tables rather than lens formulas: panoramas and measured ray maps."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import from_latlon, normalize, to_latlon
from .base import Camera, check_finite
from .resize import moved


class Equirectangular(Camera):
    """Equirectangular panorama, full sphere or a latitude/longitude crop.

    Its camera frame is the sphere frame (x forward, y left, z up), so the default
    ``rotation`` is the identity. Pixel centres: lon = lon1 - (lon1 - lon0)(u + 0.5)/W and
    lat = lat1 - (lat1 - lat0)(v + 0.5)/H, which for the full sphere is DESIGN.md's
    lon = pi - 2 pi (u + 0.5)/W, lat = pi/2 - pi (v + 0.5)/H. The image's right is the
    viewer's right, as in every real panorama and in the other camera models: y points
    left, so longitude decreases to the right.
    """

    model = "equirectangular"
    optical_axis = np.array([1.0, 0.0, 0.0])

    def __init__(self, width, height, lat_range=(-math.pi / 2, math.pi / 2),
                 lon_range=(-math.pi, math.pi), rotation=None):
        super().__init__(width, height, np.eye(3) if rotation is None else rotation)
        self.lat_range = tuple(check_finite("lat_range", lat_range).tolist())
        self.lon_range = tuple(check_finite("lon_range", lon_range).tolist())
        (a, b), (c, d) = self.lat_range, self.lon_range
        if not -math.pi / 2 <= a < b <= math.pi / 2:
            raise ValueError(f"lat_range must be increasing within [-pi/2, pi/2], got {self.lat_range}")
        if not (c < d and d - c <= 2 * math.pi + 1e-12):
            raise ValueError(f"lon_range must be increasing and span at most 2 pi, got {self.lon_range}")
        self.wraps_u = abs((d - c) - 2 * math.pi) < 1e-12
        mid = from_latlon(0.5 * (a + b), 0.5 * (c + d))
        self.optical_axis = mid

    @classmethod
    def from_photo_sphere(cls, gpano: dict, width: int, height: int) -> Equirectangular:
        """The panorama that a Photo Sphere's XMP describes (``gpano``: its GPano fields,
        :func:`usf_graph.fileio.read_photo_sphere`) for its image, ``width x height``: the
        part of the full sphere its cropped area covers (a phone's panorama that stops short
        of the poles, or of 360 degrees), scaled where the image was resized since."""
        def number(key, default=None):
            value = gpano.get(key, default)
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"the Photo Sphere metadata's {key} is {value!r}, not a number") from None
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"the Photo Sphere metadata's {key} is {value:g}")
            return value

        kind = str(gpano.get("ProjectionType", "equirectangular")).lower()
        if kind != "equirectangular":
            raise ValueError(f"the Photo Sphere metadata says projection {kind!r}; only "
                             "equirectangular panoramas are read from it: give the camera")
        fw, fh = number("FullPanoWidthPixels"), number("FullPanoHeightPixels")
        cw = number("CroppedAreaImageWidthPixels", fw)
        ch = number("CroppedAreaImageHeightPixels", fh)
        left, top = number("CroppedAreaLeftPixels", 0), number("CroppedAreaTopPixels", 0)
        if min(fw, fh, cw, ch) <= 0 or left + cw > fw + 0.5 or top + ch > fh + 0.5:
            raise ValueError(f"the Photo Sphere metadata's cropped area ({cw:g}x{ch:g} at "
                             f"{left:g}, {top:g}) does not lie in its full panorama "
                             f"({fw:g}x{fh:g})")
        if abs(width / cw - height / ch) > 0.01 * width / cw:
            raise ValueError(f"the image is {width}x{height}, but its Photo Sphere metadata's "
                             f"cropped area is {cw:g}x{ch:g}, another shape: give the camera")
        lon1 = math.pi - 2 * math.pi * left / fw
        lat1 = math.pi / 2 - math.pi * top / fh
        return cls(width, height, (max(lat1 - math.pi * ch / fh, -math.pi / 2), lat1),
                   (lon1 - 2 * math.pi * min(cw / fw, 1.0), lon1))

    @property
    def whole_sphere(self) -> bool:
        """Whether the panorama covers the whole sphere, 360 by 180 degrees (no crop)."""
        return self.wraps_u and self.lat_range == (-math.pi / 2, math.pi / 2)

    def pixels_with_rays(self) -> np.ndarray:
        """Every pixel has a ray, unless a field of view limits it (computed then)."""
        if self.fov_limit is None:
            return np.ones((self.height, self.width), bool)
        return super().pixels_with_rays()

    def pixel_rays(self):
        """A row's latitude and a column's longitude multiplied out (4x faster than
        :meth:`unproject` of every pixel), unless a field of view limits them."""
        if self.fov_limit is not None:
            return super().pixel_rays()
        lat, _, lat_ok = self._latlon(0.0, np.arange(self.height, dtype=np.float64))
        _, lon, lon_ok = self._latlon(np.arange(self.width, dtype=np.float64), 0.0)
        c = np.cos(lat)[:, None]
        rays = np.empty((self.height, self.width, 3))
        rays[..., 0], rays[..., 1] = c * np.cos(lon), c * np.sin(lon)
        rays[..., 2] = np.sin(lat)[:, None]
        valid = lat_ok[:, None] & lon_ok[None, :]
        return np.where(valid[..., None], rays, np.nan), valid

    def params(self) -> dict:
        return dict(width=self.width, height=self.height, lat_range=list(self.lat_range),
                    lon_range=list(self.lon_range))

    def _resized(self, width, height, sx, sy) -> Equirectangular:
        return Equirectangular(width, height, self.lat_range, self.lon_range, self.rotation)

    def _latlon(self, u, v):
        """Pixel coordinates -> (latitude clipped to the poles, longitude, in the panorama)."""
        (a, b), (c, d) = self.lat_range, self.lon_range
        lon = d - (d - c) * (np.asarray(u) + 0.5) / self.width
        lat = b - (b - a) * (np.asarray(v) + 0.5) / self.height
        ok = (lat >= a - 1e-12) & (lat <= b + 1e-12) & (self.wraps_u | ((lon >= c - 1e-12) & (lon <= d + 1e-12)))
        return np.clip(lat, -math.pi / 2, math.pi / 2), lon, ok

    def _unproject(self, uv):
        lat, lon, ok = self._latlon(uv[..., 0], uv[..., 1])
        return from_latlon(lat, lon), ok

    def _project(self, rays):
        (a, b), (c, d) = self.lat_range, self.lon_range
        lat, lon = to_latlon(normalize(rays))
        lon = d - np.mod(d - lon, 2 * math.pi)  # into (d - 2 pi, d]
        u = (d - lon) / (d - c) * self.width - 0.5
        v = (b - lat) / (b - a) * self.height - 0.5
        ok = (lat >= a - 1e-12) & (lat <= b + 1e-12) & (self.wraps_u | (lon >= c - 1e-12))
        return np.stack([u, v], -1), ok


class LensNormalMap(Camera):
    """A measured per-pixel ray table, for lenses no formula describes.

    ``rays [H, W, 3]`` are directions in the optical frame (any norm; NaN or zero rows
    and ``valid`` False mark pixels without a ray). ``unproject`` interpolates the table
    bilinearly; ``project`` finds the sub-pixel position whose interpolated ray matches,
    by Gauss-Newton from the nearest table entry, and marks points that do not converge
    (rays the table does not cover) invalid.
    """

    model = "lens-normal-map"

    def __init__(self, rays, valid=None, rotation=None, source=None):
        rays = np.asarray(rays, np.float64)
        if rays.ndim != 3 or rays.shape[-1] != 3 or min(rays.shape[:2]) < 2:
            raise ValueError(f"a lens normal map must have shape [H, W, 3] with H, W >= 2, got {rays.shape}")
        super().__init__(rays.shape[1], rays.shape[0], rotation)
        n = np.linalg.norm(rays, axis=-1)
        ok = np.isfinite(n) & (n > 0)
        if valid is not None:
            valid = np.asarray(valid, bool)
            if valid.shape != rays.shape[:2]:
                raise ValueError(f"valid must have shape {rays.shape[:2]}, got {valid.shape}")
            ok &= valid
        if not ok.any():
            raise ValueError("the lens normal map has no valid pixel (all rays NaN, zero or masked)")
        self.rays = np.where(ok[..., None], rays / np.where(ok, n, 1)[..., None], 0.0)
        self.valid_table = ok
        self.source = None if source is None else str(source)
        idx = np.flatnonzero(ok)
        self._tree = cKDTree(self.rays.reshape(-1, 3)[idx])
        self._tree_idx = idx

    @classmethod
    def from_file(cls, path, rotation=None) -> LensNormalMap:
        """Load ``.npy`` ([H, W, 3]) or ``.npz`` (keys ``rays`` and optional ``valid``)."""
        path = Path(path)
        try:
            data = np.load(path, allow_pickle=False)
        except Exception as e:  # noqa: BLE001 - numpy raises many kinds here
            raise ValueError(f"cannot read lens normal map {path}: {e}") from e
        if isinstance(data, np.lib.npyio.NpzFile):
            if "rays" not in data:
                raise ValueError(f"{path} has no 'rays' array (found {list(data.keys())})")
            return cls(data["rays"], data["valid"] if "valid" in data else None, rotation, path)
        return cls(data, None, rotation, path)

    def params(self) -> dict:
        # The table itself is the parameter set; the key holds a digest of it.
        import hashlib

        h = hashlib.sha256(self.rays.tobytes() + self.valid_table.tobytes()).hexdigest()[:16]
        return dict(width=self.width, height=self.height, digest=h, source=self.source)

    def save(self, path) -> None:
        """Refuses: a ray table has no calibration file format; save its arrays with numpy."""
        raise ValueError("a LensNormalMap is its table: save it with "
                         "numpy.savez(path, rays=cam.rays, valid=cam.valid_table)")

    def _resized(self, width, height, sx, sy) -> LensNormalMap:
        # each new pixel's ray, from where it lies in the table (its own interpolation)
        u, v = np.meshgrid(moved(np.arange(width), 1 / sx), moved(np.arange(height), 1 / sy))
        rays, ok = self.unproject(np.stack([u, v], -1))
        return LensNormalMap(rays, ok, self.rotation, self.source)

    def _rebuild(self, rotation) -> LensNormalMap:
        return LensNormalMap(self.rays, self.valid_table, rotation, self.source)

    def _cell(self, uv):
        # the outer half pixel extrapolates its cell linearly, as a lens model would
        u = np.clip(uv[..., 0], -0.5, self.width - 0.5)
        v = np.clip(uv[..., 1], -0.5, self.height - 0.5)
        j = np.clip(np.floor(u).astype(np.int64), 0, self.width - 2)
        i = np.clip(np.floor(v).astype(np.int64), 0, self.height - 2)
        T, V = self.rays, self.valid_table
        c = [T[i, j], T[i, j + 1], T[i + 1, j], T[i + 1, j + 1]]
        ok = V[i, j] & V[i, j + 1] & V[i + 1, j] & V[i + 1, j + 1]
        return (u - j)[..., None], (v - i)[..., None], c, ok

    def _interp(self, uv, jacobian=False):
        fu, fv, (a, b, c, d), ok = self._cell(uv)
        r = (1 - fv) * ((1 - fu) * a + fu * b) + fv * ((1 - fu) * c + fu * d)
        if not jacobian:
            return r, ok
        return r, ok, (1 - fv) * (b - a) + fv * (d - c), (1 - fu) * (c - a) + fu * (d - b)

    def _unproject(self, uv):
        inside = (uv[..., 0] >= -0.5) & (uv[..., 0] <= self.width - 0.5) & \
                 (uv[..., 1] >= -0.5) & (uv[..., 1] <= self.height - 0.5)
        r, ok = self._interp(uv)
        n = np.linalg.norm(r, axis=-1, keepdims=True)
        return r / np.where(n > 0, n, 1), ok & inside & (n[..., 0] > 0)

    def _project(self, rays):
        target = normalize(rays)
        shape = target.shape[:-1]
        t = target.reshape(-1, 3)
        _, k = self._tree.query(t)
        flat = self._tree_idx[k]
        uv = np.stack([flat % self.width, flat // self.width], -1).astype(np.float64)
        for _ in range(30):
            r, _, du, dv = self._interp(uv, jacobian=True)
            n = np.linalg.norm(r, axis=-1, keepdims=True)
            n = np.where(n > 0, n, np.nan)  # a cell with a hole has no ray: no step
            p = r / n
            # derivative of the normalized ray, projected off its radial component
            du = (du - p * (p * du).sum(-1, keepdims=True)) / n
            dv = (dv - p * (p * dv).sum(-1, keepdims=True)) / n
            res = p - t
            a, b, c = (du * du).sum(-1), (du * dv).sum(-1), (dv * dv).sum(-1)
            gu, gv = (du * res).sum(-1), (dv * res).sum(-1)
            det = a * c - b * b
            det = np.where(np.abs(det) > 1e-300, det, np.nan)
            step = np.stack([(c * gu - b * gv) / det, (a * gv - b * gu) / det], -1)
            step = np.where(np.isfinite(step), step, 0.0)  # stays put; the check below fails it
            uv = uv - step
            uv[..., 0] = np.clip(uv[..., 0], -0.5, self.width - 0.5)
            uv[..., 1] = np.clip(uv[..., 1], -0.5, self.height - 0.5)
            if np.all(np.abs(step) < 1e-13):
                break
        back, ok = self._unproject(uv)
        ok &= np.linalg.norm(back - t, axis=-1) < 1e-11
        return uv.reshape(*shape, 2), ok.reshape(shape)
