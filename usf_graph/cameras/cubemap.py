"""Cube maps: six 90-degree faces in one image, the format of skyboxes, game engines,
many panorama tools and 360 video.

The faces and their orientation are py360convert's (the tests check against it): front
(+x), right (-y), back (-x), left (+y), each upright, then up (+z, its top towards the
back) and down (-z, its top towards the front), every face's right the viewer's right.
Layouts (:data:`LAYOUTS`; the tests check the last two against FFmpeg's ``v360``
filter)::

    horizon (py360convert)   F R B L U D
    dice (py360convert)        U
                             L F R B
                               D
    c6x1 (FFmpeg)            R L U D F B
    c3x2 (FFmpeg)            R L U
                             D F B

YouTube's equi-angular cube map, whose faces are turned in their cells and sampled
evenly in angle, is :class:`EquiAngularCubemap`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..geometry import normalize, rotation_from_axis_angle
from .base import DEFAULT_ROTATION, Camera, _triangle_solid_angle, check_positive
from .pinhole import Pinhole

#: The faces, in py360convert's order.
FACES = ("front", "right", "back", "left", "up", "down")


class Layout(NamedTuple):
    """Where each face of :data:`FACES` sits in a layout (``cells``: column, row, in face
    sizes), and the layout's size in faces (``shape``: columns, rows)."""

    cells: tuple
    shape: tuple


#: The layouts by name (module docstring).
LAYOUTS = {"horizon": Layout(((0, 0), (1, 0), (2, 0), (3, 0), (4, 0), (5, 0)), (6, 1)),
           "dice": Layout(((1, 1), (2, 1), (3, 1), (0, 1), (1, 0), (1, 2)), (4, 3)),
           "c6x1": Layout(((4, 0), (0, 0), (5, 0), (1, 0), (2, 0), (3, 0)), (6, 1)),
           "c3x2": Layout(((1, 1), (0, 0), (2, 1), (1, 0), (2, 0), (0, 1)), (3, 2))}
_TURNS = {"front": ((0.0, 0.0, 1.0), 0.0), "right": ((0.0, 0.0, 1.0), -0.5),
          "back": ((0.0, 0.0, 1.0), 1.0), "left": ((0.0, 0.0, 1.0), 0.5),
          "up": ((0.0, 1.0, 0.0), -0.5), "down": ((0.0, 1.0, 0.0), 0.5)}


def face_rotation(face: str, turns: int = 0) -> np.ndarray:
    """``[3, 3]`` sphere <- optical frame of a cube face (:data:`FACES`): the front face
    turned by a quarter or half turn about z (the sides) or y (up and down); ``turns``:
    the face's image then turned by that many quarter turns in its cell (a layout's)."""
    if face not in _TURNS:
        raise ValueError(f"unknown cube face {face!r}; the faces are {', '.join(FACES)}")
    axis, half_turns = _TURNS[face]
    roll = rotation_from_axis_angle(np.array([0.0, 0.0, 1.0]), turns * math.pi / 2)
    return rotation_from_axis_angle(np.array(axis), half_turns * math.pi) @ DEFAULT_ROTATION @ roll


def _face_of() -> np.ndarray:
    """``[3, 2]``: the index in :data:`FACES` of the face looking along each axis of the
    sphere frame (x, y, z), negative and positive: where its optical axis points."""
    out = np.empty((3, 2), np.int64)
    for k, face in enumerate(FACES):
        z = face_rotation(face)[:, 2]
        axis = int(np.argmax(np.abs(z)))
        out[axis, int(z[axis] > 0)] = k
    return out


def _per_face(v: np.ndarray, k: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``v [..., 3] @ R[k]``, each vector by its face's matrix (one product per face)."""
    out = np.empty_like(v)
    for f in range(len(R)):
        on = k == f
        out[on] = v[on] @ R[f]
    return out


def _onto_faces(rays: np.ndarray, face_of: np.ndarray, R: np.ndarray):
    """Each ray's face (the one it points most towards: its largest coordinate and that
    one's sign; ``face_of`` as :func:`_face_of`'s) and the ray in that face's optical
    frame (``R [6, 3, 3]``)."""
    axis = np.argmax(np.abs(rays), -1)
    positive = np.take_along_axis(rays, axis[..., None], -1)[..., 0] > 0
    k = face_of[axis, positive.astype(np.int64)]
    return k, _per_face(rays, k, R)


def cube_faces(size: int) -> dict[str, Pinhole]:
    """The six faces as pinholes without distortion, ``size`` pixels square (90 degrees
    from pixel edge to pixel edge), mounted in the sphere frame: a cube map as a rig."""
    size = _face_size(size)
    f, c = size / 2, (size - 1) / 2
    return {k: Pinhole(f, f, c, c, size, size, rotation=face_rotation(k)) for k in FACES}


def _face_size(size) -> int:
    if int(size) != size or size < 2:
        raise ValueError(f"a cube face is a whole number of pixels, at least 2, got {size}")
    return int(size)


def _layout(layout: str) -> Layout:
    if layout not in LAYOUTS:
        raise ValueError(f"unknown cube map layout {layout!r}; known: {', '.join(LAYOUTS)}")
    return LAYOUTS[layout]


class Cubemap(Camera):
    """A cube map: six 90-degree faces, ``size`` pixels square, in one image laid out as
    ``layout`` (:data:`LAYOUTS`; ``horizon``, ``c6x1``: ``6 size x size``; ``dice``: ``4
    size x 3 size``, its six empty cells without rays; ``c3x2``: ``3 size x 2 size``). Its
    frame is the sphere frame, as a panorama's.

    A ray is seen by the face it points most towards; on a face, pixel centres lie at
    ``u = size/2 * x/z + (size - 1)/2`` (and ``v`` alike) of the face's optical frame, plus
    the face's place in the layout. Sampling keeps each point on its own face: where a
    point lies within half a pixel of a face's edge it reads the face's edge pixel, never
    the next cell of the layout, which is another face or empty."""

    model = "cubemap"
    optical_axis = np.array([1.0, 0.0, 0.0])

    def __init__(self, size: int, layout: str = "horizon", rotation=None):
        self.size = _face_size(check_positive("size", size))
        spec = _layout(layout)
        cols, rows = spec.shape
        super().__init__(cols * self.size, rows * self.size, np.eye(3) if rotation is None else rotation)
        self.layout = layout
        self._R = np.stack([face_rotation(k) for k in FACES])  # [6, 3, 3]
        self._cells = np.array(spec.cells, np.int64)  # [6, 2] column, row
        self._face_of = _face_of()
        self._face_at = np.full((rows, cols), -1, np.int64)
        for k, (col, row) in enumerate(spec.cells):
            self._face_at[row, col] = k

    def params(self) -> dict:
        return dict(size=self.size, layout=self.layout)

    def _resized(self, width, height, sx, sy) -> Cubemap:
        cols, rows = _layout(self.layout).shape
        if width % cols or height % rows or width // cols != height // rows:
            raise ValueError(f"a {self.layout} cube map is {cols} by {rows} square faces: "
                             f"{width}x{height} is not")
        return Cubemap(width // cols, self.layout, self.rotation)

    def _project(self, rays):
        k, p = _onto_faces(rays, self._face_of, self._R)
        half, c = self.size / 2, (self.size - 1) / 2
        uv = half * p[..., :2] / p[..., 2:] + c + self._cells[k] * self.size
        return uv, np.ones(uv.shape[:-1], bool)

    def _unproject(self, uv):
        cell = np.floor((uv + 0.5) / self.size).astype(np.int64)
        rows, cols = self._face_at.shape
        inside = (cell[..., 0] >= 0) & (cell[..., 0] < cols) & (cell[..., 1] >= 0) & (cell[..., 1] < rows)
        k = self._face_at[np.clip(cell[..., 1], 0, rows - 1), np.clip(cell[..., 0], 0, cols - 1)]
        ok = inside & (k >= 0)
        k = np.where(ok, k, 0)
        half, c = self.size / 2, (self.size - 1) / 2
        local = np.ones(uv.shape[:-1] + (3,))
        local[..., :2] = (uv - self._cells[k] * self.size - c) / half
        return normalize(_per_face(local, k, self._R.transpose(0, 2, 1))), ok

    def pixel_rays(self):
        """One face's rays turned onto each face (6x faster than :meth:`unproject` of every
        pixel), unless a field of view limits them."""
        if self.fov_limit is not None:
            return super().pixel_rays()
        s = self.size
        local = cube_faces(s)["front"].pixel_rays()[0]  # a face's rays in its optical frame
        rays = np.full((self.height, self.width, 3), np.nan)
        for k, (col, row) in enumerate(self._cells):
            rays[row * s:(row + 1) * s, col * s:(col + 1) * s] = local @ self._R[k].T
        return rays, self.pixels_with_rays()

    def pixels_with_rays(self) -> np.ndarray:
        """The faces' pixels (not the layout's empty cells), unless a field of view limits
        them (computed then)."""
        if self.fov_limit is not None:
            return super().pixels_with_rays()
        return np.repeat(np.repeat(self._face_at >= 0, self.size, 0), self.size, 1)

    def pixel_solid_angles(self) -> np.ndarray:
        """Solid angle (sr) of each pixel ``[H, W]``, each face's from its own corners (the
        six are alike), 0 in the layout's empty cells and where :attr:`image_mask` ignores
        a pixel."""
        face = cube_faces(self.size)["front"].pixel_solid_angles()
        out = np.zeros((self.height, self.width))
        s = self.size
        for col, row in self._cells:
            out[row * s:(row + 1) * s, col * s:(col + 1) * s] = face
        return out if self.image_mask is None else np.where(self.image_mask, out, 0.0)

    def sample_positions(self, u, v):
        """Where to sample the image for points at ``(u, v)``: within the face each lies
        on (the cell it falls in), the face's edge pixel within half a pixel of its edge."""
        s = self.size
        col = np.clip(np.floor((u + 0.5) / s), 0, self.width // s - 1)
        row = np.clip(np.floor((v + 0.5) / s), 0, self.height // s - 1)
        return np.clip(u, col * s, col * s + s - 1), np.clip(v, row * s, row * s + s - 1)


#: YouTube's equi-angular cube map: each face of :data:`FACES` in its cell (column, row),
#: turned by quarter turns counter-clockwise (as :func:`face_rotation`'s ``turns``)::
#:
#:     L F R
#:     D B U    (D and U a quarter turn counter-clockwise, B clockwise)
EAC_CELLS = ((1, 0), (2, 0), (1, 1), (0, 0), (2, 1), (0, 1))
EAC_TURNS = (0, 0, 3, 0, 1, 1)


class EquiAngularCubemap(Camera):
    r"""YouTube's equi-angular cube map (EAC), as FFmpeg's ``v360`` filter reads and writes
    it (``eac``; the tests check against it): six faces in a ``width x height`` image, 3
    wide and 2 high (:data:`EAC_CELLS`, the bottom row turned), each sampled evenly in
    angle rather than in tangent, so that pixels span about equal angles (across a face,
    ``a = 4/pi * atan(x/z)`` in [-1, 1] is linear in the pixels).

    As in YouTube's streams, ``padding`` pixels (2) border the image on the left and
    right and each row above and below: with them, a face is ``(width - 2 padding) / 3``
    pixels wide and ``height / 2 - 2 padding`` high, not necessarily whole numbers.
    Padding pixels have no ray. Sampling keeps each point on its own face, whose
    neighbours in a row meet without padding."""

    model = "eac"
    optical_axis = np.array([1.0, 0.0, 0.0])

    def __init__(self, width: int, height: int, padding: float = 2.0, rotation=None):
        for name, v in (("width", width), ("height", height)):
            if int(v) != v or v < 6:
                raise ValueError(f"the image {name} must be a whole number of at least 6 pixels, got {v}")
        if not (math.isfinite(padding) and 0 <= padding and 2 * padding < min(width / 3, height / 2) / 2):
            raise ValueError(f"padding must be at least 0 and leave most of each face, got {padding}")
        super().__init__(int(width), int(height), np.eye(3) if rotation is None else rotation)
        self.padding = float(padding)
        self._R = np.stack([face_rotation(k, q) for k, q in zip(FACES, EAC_TURNS)])
        self._cells = np.array(EAC_CELLS, np.int64)
        self._face_of = _face_of()
        self._face_at = np.empty((2, 3), np.int64)
        for k, (col, row) in enumerate(EAC_CELLS):
            self._face_at[row, col] = k

    def params(self) -> dict:
        return dict(width=self.width, height=self.height, padding=self.padding)

    def _resized(self, width, height, sx, sy) -> EquiAngularCubemap:
        if not math.isclose(sx, sy, rel_tol=1e-3):
            raise ValueError(f"an equi-angular cube map resizes by one factor both ways: "
                             f"{self.width}x{self.height} -> {width}x{height} is not")
        return EquiAngularCubemap(width, height, self.padding * sx, self.rotation)

    # pixel (u, v) covers [u - 1/2, u + 1/2]; a face spans [0, 1] across its cell
    @property
    def face_shape(self) -> tuple[float, float]:
        """A face's width and height in pixels (not necessarily whole numbers)."""
        return (self.width - 2 * self.padding) / 3, self.height / 2 - 2 * self.padding

    def _edges(self, col, row):
        """Pixel coordinates of the left and top edges of the faces in cells ``(col, row)``."""
        return (self.padding + (self.width - 2 * self.padding) * np.asarray(col) / 3 - 0.5,
                self.height / 2 * np.asarray(row) + self.padding - 0.5)

    def _project(self, rays):
        k, p = _onto_faces(rays, self._face_of, self._R)
        st = np.arctan(p[..., :2] / p[..., 2:]) * (2 / math.pi) + 0.5  # [0, 1] across the face
        fw, fh = self.face_shape
        u0, v0 = self._edges(self._cells[k, 0], self._cells[k, 1])
        uv = np.stack([u0 + st[..., 0] * fw, v0 + st[..., 1] * fh], -1)
        return uv, np.ones(uv.shape[:-1], bool)

    def _cell(self, uv):
        """Each point's cell (column, row), its place ``[0, 1]`` across the face there, and
        whether it is on the face (not in the padding, nor outside the image)."""
        p, (fw, fh) = self.padding, self.face_shape
        s = (uv[..., 0] + 0.5 - p) / fw
        row = np.floor((uv[..., 1] + 0.5) / (self.height / 2))
        t = (uv[..., 1] + 0.5 - row * self.height / 2 - p) / fh
        col = np.floor(s)
        ok = (s >= 0) & (s <= 3) & (row >= 0) & (row <= 1) & (t >= 0) & (t <= 1)
        col = np.clip(col, 0, 2).astype(np.int64)
        return col, np.clip(row, 0, 1).astype(np.int64), s - col, t, ok

    def _unproject(self, uv):
        col, row, s, t, ok = self._cell(uv)
        k = self._face_at[row, col]
        local = np.ones(uv.shape[:-1] + (3,))
        local[..., 0] = np.tan((s - 0.5) * (math.pi / 2))
        local[..., 1] = np.tan((t - 0.5) * (math.pi / 2))
        return normalize(_per_face(local, k, self._R.transpose(0, 2, 1))), ok

    def _axes(self):
        """Per column: its cell's column, place across the face and whether it is on one
        (not the padding); per row, the same: a face's pixels are the products."""
        u = np.arange(self.width, dtype=np.float64)
        v = np.arange(self.height, dtype=np.float64)
        u0, v0 = self._edges(0, 0)  # along the first face's middle row and column
        fw, fh = self.face_shape
        col, _, s, _, col_ok = self._cell(np.stack([u, np.full_like(u, v0 + fh / 2)], -1))
        _, row, _, t, row_ok = self._cell(np.stack([np.full_like(v, u0 + fw / 2), v], -1))
        return (col, s, col_ok), (row, t, row_ok)

    def pixels_with_rays(self) -> np.ndarray:
        """The faces' pixels (not the padding's), from where they lie alone, unless a field
        of view limits them (computed then)."""
        if self.fov_limit is not None:
            return super().pixels_with_rays()
        (_, _, col_ok), (_, _, row_ok) = self._axes()
        return row_ok[:, None] & col_ok[None, :]

    def pixel_rays(self):
        """Each face's rays multiplied out from its columns' and rows' angles (faster than
        :meth:`unproject` of every pixel), unless a field of view limits them."""
        if self.fov_limit is not None:
            return super().pixel_rays()
        (col, s, col_ok), (row, t, row_ok) = self._axes()
        tx, ty = np.tan((s - 0.5) * (math.pi / 2)), np.tan((t - 0.5) * (math.pi / 2))
        rays = np.full((self.height, self.width, 3), np.nan)
        for k, (c, r) in enumerate(EAC_CELLS):
            us, vs = np.flatnonzero(col_ok & (col == c)), np.flatnonzero(row_ok & (row == r))
            local = np.ones((len(vs), len(us), 3))
            local[..., 0], local[..., 1] = tx[us][None, :], ty[vs][:, None]
            rays[np.ix_(vs, us)] = normalize(local) @ self._R[k].T
        return rays, row_ok[:, None] & col_ok[None, :]

    def pixel_solid_angles(self) -> np.ndarray:
        """Solid angle (sr) of each pixel ``[H, W]``, from its corners on its own face (a
        row's faces meet edge to edge, but the rows do not), 0 in the padding and where
        :attr:`image_mask` ignores a pixel."""
        col, row, s, t, ok = self._cell(self.pixel_grid())
        fw, fh = self.face_shape
        corners = []
        for du, dv in ((-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5)):
            local = np.ones(s.shape + (3,))  # in the face's frame: areas do not turn
            local[..., 0] = np.tan((s + du / fw - 0.5) * (math.pi / 2))
            local[..., 1] = np.tan((t + dv / fh - 0.5) * (math.pi / 2))
            corners.append(normalize(local))
        a, b, c, d = corners
        om = _triangle_solid_angle(a, b, c) + _triangle_solid_angle(a, c, d)
        if self.image_mask is not None:
            ok = ok & self.image_mask
        return np.where(ok, om, 0.0)

    def sample_positions(self, u, v):
        """Where to sample the image for points at ``(u, v)``: among the pixels whose
        centres lie on the point's own face (its cell's), the padding's never."""
        col, row, _, _, _ = self._cell(np.stack([np.asarray(u, np.float64), np.asarray(v, np.float64)], -1))
        (fw, fh), (u0, v0) = self.face_shape, self._edges(col, row)
        return (np.clip(u, np.ceil(u0), np.ceil(u0 + fw) - 1),
                np.clip(v, np.ceil(v0), np.ceil(v0 + fh) - 1))


__all__ = ["FACES", "LAYOUTS", "Layout", "Cubemap", "EquiAngularCubemap", "EAC_CELLS", "EAC_TURNS",
           "cube_faces", "face_rotation"]
