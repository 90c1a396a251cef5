"""Cube maps: six 90-degree pinhole faces in one image, the format of skyboxes, game
engines and many panorama tools.

The faces, their order and their orientation are py360convert's (the tests check against
it): front (+x), right (-y), back (-x), left (+y), each upright, then up (+z, its top
towards the back) and down (-z, its top towards the front), every face's right the
viewer's right. Layouts: ``horizon``, the six in a row, and ``dice``, a cross 4 faces wide
and 3 high::

        U
      L F R B
        D
"""

from __future__ import annotations

import math

import numpy as np

from ..geometry import normalize, rotation_from_axis_angle
from .base import DEFAULT_ROTATION, Camera, check_positive
from .pinhole import Pinhole

#: The faces, in py360convert's order.
FACES = ("front", "right", "back", "left", "up", "down")
#: Where each face of :data:`FACES` sits in a layout (column, row, in face sizes), and the
#: layout's size in faces (columns, rows).
LAYOUTS = {"horizon": (((0, 0), (1, 0), (2, 0), (3, 0), (4, 0), (5, 0)), (6, 1)),
           "dice": (((1, 1), (2, 1), (3, 1), (0, 1), (1, 0), (1, 2)), (4, 3))}
_TURNS = {"front": ((0.0, 0.0, 1.0), 0.0), "right": ((0.0, 0.0, 1.0), -0.5),
          "back": ((0.0, 0.0, 1.0), 1.0), "left": ((0.0, 0.0, 1.0), 0.5),
          "up": ((0.0, 1.0, 0.0), -0.5), "down": ((0.0, 1.0, 0.0), 0.5)}


def face_rotation(face: str) -> np.ndarray:
    """``[3, 3]`` sphere <- optical frame of a cube face (:data:`FACES`): the front face
    turned by a quarter or half turn about z (the sides) or y (up and down)."""
    if face not in _TURNS:
        raise ValueError(f"unknown cube face {face!r}; the faces are {', '.join(FACES)}")
    axis, turns = _TURNS[face]
    return rotation_from_axis_angle(np.array(axis), turns * math.pi) @ DEFAULT_ROTATION


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


def _layout(layout: str):
    if layout not in LAYOUTS:
        raise ValueError(f"unknown cube map layout {layout!r}; known: {', '.join(LAYOUTS)}")
    return LAYOUTS[layout]


class Cubemap(Camera):
    """A cube map: six 90-degree faces, ``size`` pixels square, in one image laid out as
    ``layout`` (``horizon``: ``6 size x size``; ``dice``: ``4 size x 3 size``, its six
    empty cells without rays). Its frame is the sphere frame, as a panorama's.

    A ray is seen by the face it points most towards; on a face, pixel centres lie at
    ``u = size/2 * x/z + (size - 1)/2`` (and ``v`` alike) of the face's optical frame, plus
    the face's place in the layout. Sampling keeps each point on its own face: where a
    point lies within half a pixel of a face's edge it reads the face's edge pixel, never
    the next cell of the layout, which is another face or empty."""

    model = "cubemap"
    optical_axis = np.array([1.0, 0.0, 0.0])

    def __init__(self, size: int, layout: str = "horizon", rotation=None):
        self.size = _face_size(check_positive("size", size))
        cells, (cols, rows) = _layout(layout)
        super().__init__(cols * self.size, rows * self.size, np.eye(3) if rotation is None else rotation)
        self.layout = layout
        self._R = np.stack([face_rotation(k) for k in FACES])  # [6, 3, 3]
        self._cells = np.array(cells, np.int64)  # [6, 2] column, row
        self._face_of = _face_of()
        self._face_at = np.full((rows, cols), -1, np.int64)
        for k, (col, row) in enumerate(cells):
            self._face_at[row, col] = k

    def params(self) -> dict:
        return dict(size=self.size, layout=self.layout)

    def _resized(self, width, height, sx, sy) -> Cubemap:
        cols, rows = _layout(self.layout)[1]
        if width % cols or height % rows or width // cols != height // rows:
            raise ValueError(f"a {self.layout} cube map is {cols} by {rows} square faces: "
                             f"{width}x{height} is not")
        return Cubemap(width // cols, self.layout, self.rotation)

    def _project(self, rays):
        # the face the ray points most towards: its largest coordinate and that one's sign
        axis = np.argmax(np.abs(rays), -1)
        positive = np.take_along_axis(rays, axis[..., None], -1)[..., 0] > 0
        k = self._face_of[axis, positive.astype(np.int64)]
        p = _per_face(rays, k, self._R)  # in the face's optical frame
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


__all__ = ["FACES", "LAYOUTS", "Cubemap", "cube_faces", "face_rotation"]
