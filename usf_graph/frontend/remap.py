"""One ``cv2.remap`` that samples a camera's images at many fixed points: the fast path of
lifting (onto a grid) and of re-imaging (into another camera's pixels)."""

from __future__ import annotations

import copy
import math

import cv2
import numpy as np

from ..cameras import Camera
from .interpolation import bilinear_entries, valid_entries

REMAP_DTYPES = (np.uint8, np.uint16, np.int16, np.float32)
_ROW = 1024  # cv2.remap maps must be narrower than SHRT_MAX, so fold M points into rows
_OUTSIDE = -16.0  # unseen points sample far outside the image: 0 under BORDER_CONSTANT


def round_to(values: np.ndarray, dtype) -> np.ndarray:
    """``values`` in ``dtype``: rounded and clipped to its range for an integer type, as
    ``cv2.remap`` gives integer images; cast as they are for a float one."""
    dtype = np.dtype(dtype)
    if dtype.kind not in "iu":
        return values.astype(dtype, copy=False)
    info = np.iinfo(dtype)
    return np.clip(np.round(values), info.min, info.max).astype(dtype)


class Remap:
    r"""Samples images of ``camera`` at ``M`` points with one ``cv2.remap``.

    Args:
        camera: the camera whose images are sampled.
        uv: ``[M, 2]`` pixel coordinates of the points (anything where not ``seen``).
        seen: ``[M]`` bool, the points to sample; the others are 0.
        interpolation: ``bilinear`` or ``nearest``.
        valid: ``[H, W]`` bool, the pixels that may be read
            (:func:`~usf_graph.frontend.interpolation.valid_pixels`).

    ``cv2.remap`` blends a point's four pixels whatever they hold. The interpolation tables
    leave out pixels without a ray or masked ones and renormalize over the rest, so the few
    points next to such pixels (the *border*) are recomputed that way, reading only their
    valid pixels. Weights are OpenCV's (coordinates to 1/32 pixel), and integer images come
    back as ``cv2.remap`` gives them, rounded (``keep_dtype``) or as float32.
    """

    def __init__(self, camera: Camera, uv: np.ndarray, seen: np.ndarray, interpolation: str,
                 valid: np.ndarray):
        if interpolation not in ("bilinear", "nearest"):
            raise ValueError(f"cv2.remap samples bilinear or nearest, not {interpolation!r}")
        self.camera, self.interpolation = camera, interpolation
        seen = np.asarray(seen, bool)
        self.num_points = n = len(seen)
        rows = max(1, math.ceil(n / _ROW))
        u, v = camera.sample_positions(np.asarray(uv[:, 0], np.float64), np.asarray(uv[:, 1], np.float64))
        mx = np.full(rows * _ROW, _OUTSIDE, np.float32)
        my = np.full(rows * _ROW, _OUTSIDE, np.float32)
        mx[:n], my[:n] = np.where(seen, u, _OUTSIDE), np.where(seen, v, _OUTSIDE)
        self.maps = (mx.reshape(rows, _ROW), my.reshape(rows, _ROW))
        self.border_mode = cv2.BORDER_WRAP if camera.wraps_u else cv2.BORDER_CONSTANT
        self._flag = cv2.INTER_LINEAR if interpolation == "bilinear" else cv2.INTER_NEAREST
        self._seen = seen
        self._unseen = np.flatnonzero(~seen) if camera.wraps_u else None
        self._valid = np.asarray(valid, bool)
        self._some_invalid = not self._valid.all()
        self.reached = seen.copy()
        self._border = None
        if interpolation == "bilinear" and self._some_invalid:
            self._border = self._border_rows(uv, seen)

    def _border_rows(self, uv, seen):
        """The seen points whose four pixels include one that may not be read:
        ``(rows, idx [R, 4], w [R, 4])``, their entries renormalized over the valid pixels
        (``w`` all 0 where none is). None if there are none."""
        cover = cv2.remap(self._valid.astype(np.float32), *self.maps, cv2.INTER_LINEAR,
                          borderMode=self.border_mode).ravel()[:self.num_points]
        rows = np.flatnonzero(seen & (cover < 1 - 1e-4))
        if not len(rows):
            return None
        idx, w = bilinear_entries(self.camera, np.asarray(uv, np.float64)[rows], np.ones(len(rows), bool))
        w = valid_entries(self.camera, idx, w, valid=self._valid)
        self.reached[rows] = w.sum(1) > 0
        return rows, idx, w

    def restricted(self, keep: np.ndarray) -> Remap:
        """This remap over the points where ``keep`` (``[M]`` bool) alone, the others
        unseen: what building it with ``seen & keep`` gives, without finding the border
        again."""
        new = copy.copy(self)
        drop = np.flatnonzero(self._seen & ~keep)
        new.maps = tuple(m.copy() for m in self.maps)
        for m in new.maps:
            m.ravel()[drop] = _OUTSIDE
        new._seen, new.reached = self._seen & keep, self.reached & keep
        if self.camera.wraps_u:
            new._unseen = np.flatnonzero(~new._seen)
        if self._border is not None:
            rows, idx, w = self._border
            on = keep[rows]
            new._border = (rows[on], idx[on], w[on]) if on.any() else None
        return new

    @staticmethod
    def accepts(arr) -> bool:
        """Whether ``arr`` (an image ``[H, W, C]``) takes this path: numpy, a dtype
        ``cv2.remap`` interpolates, at most 4 channels."""
        return isinstance(arr, np.ndarray) and arr.dtype.type in REMAP_DTYPES and arr.shape[-1] <= 4

    def blank(self, channels: int, dtype) -> np.ndarray:
        """Zeros to write several cameras' points into (``into=`` of :meth:`__call__`)."""
        return np.zeros((self.maps[0].size, channels), dtype)

    def __call__(self, arr: np.ndarray, keep_dtype: bool = False, into: np.ndarray | None = None) -> np.ndarray:
        """``arr [H, W, C]`` -> ``[M, C]`` float32 (``keep_dtype``: ``arr``'s dtype, the
        border rounded), 0 where a point is not :attr:`reached`. With ``into`` (a
        :meth:`blank` of ``arr``'s dtype, for a camera that does not wrap) only the seen
        points are written there, the others left as they are: a rig's cameras, each
        seeing its own pixels, fill one image."""
        c = arr.shape[-1]
        # a weight OpenCV rounds to 0 times a NaN in a pixel that may not be read is NaN
        dirty = self._some_invalid and arr.dtype.kind == "f"
        if into is None:
            out = cv2.remap(arr, *self.maps, self._flag, borderMode=self.border_mode)
            if dirty and not np.isfinite(out).all():  # the image cleaned only then
                out = cv2.remap(np.where(self._valid[..., None], arr, 0), *self.maps, self._flag,
                                borderMode=self.border_mode)
        else:
            if self.camera.wraps_u or into.shape != (self.maps[0].size, c) or into.dtype != arr.dtype:
                raise ValueError("into= takes a blank() of the image's channels and type, for a "
                                 "camera that does not wrap around")
            if dirty and not np.isfinite(arr).all():
                arr = np.where(self._valid[..., None], arr, 0)
            dst = into.reshape(*self.maps[0].shape, c) if c > 1 else into.reshape(self.maps[0].shape)
            out = cv2.remap(arr, *self.maps, self._flag, dst=dst, borderMode=cv2.BORDER_TRANSPARENT)
            if not np.shares_memory(out, into):
                raise RuntimeError("cv2.remap did not write into the given array")
            out, keep_dtype = into, True
        out = out.reshape(-1, c)[:self.num_points]
        if not keep_dtype:
            out = out.astype(np.float32, copy=False)
        if self._border is not None:
            rows, idx, w = self._border
            g = arr.reshape(-1, c)[idx].astype(np.float64)
            part = (np.where(w[..., None] > 0, g, 0.0) * w[..., None]).sum(1)  # unread pixels may hold NaN
            out[rows] = round_to(part, arr.dtype) if keep_dtype else part
        if self._unseen is not None and len(self._unseen):
            out[self._unseen] = 0  # wrapped onto real pixels
        return out


__all__ = ["Remap", "REMAP_DTYPES", "round_to"]
