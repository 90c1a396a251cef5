"""Re-imaging: a camera's images as another camera would see them, through the sphere, with
the geometry built once (a video's frames, a rig's stream)."""

from __future__ import annotations

import numpy as np
import torch

from ..cameras import Camera
from .frontend import _as_image
from .interpolation import bilinear_entries, nearest_entries, valid_entries, valid_pixels
from .remap import Remap

INTERPOLATIONS = ("bilinear", "nearest")


class Reimager:
    r"""Re-images ``cam_src``'s images as ``cam_dst`` would see them: each target pixel
    takes the source image's value on its ray (the ray projected into the source camera,
    :meth:`~usf_graph.cameras.Camera.sees`), 0 where the source does not see it.

    Args:
        cam_src: the camera that took the images.
        cam_dst: the camera to see them through (its :meth:`lens_normal_map`).
        interpolation: ``bilinear``, or ``nearest`` (label images).
        source_valid: ``[H, W]`` bool, the source pixels that may be read
            (default :func:`~usf_graph.frontend.interpolation.valid_pixels`: those with a
            ray, not masked), where the caller has them.
        target: ``cam_dst``'s ``lens_normal_map()``, where the caller has it.

    Everything but the pixels depends on the two cameras only, so it is built once; each
    image is then one ``cv2.remap`` (numpy uint8/uint16/int16/float32, at most 4 channels)
    or one gather with float64-exact weights (anything else, torch included). Source pixels
    without a ray or masked are never read: a target pixel next to them blends the rest.
    """

    def __init__(self, cam_src: Camera, cam_dst: Camera, interpolation: str = "bilinear",
                 source_valid: np.ndarray | None = None,
                 target: tuple[np.ndarray, np.ndarray] | None = None):
        if interpolation not in INTERPOLATIONS:
            raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}")
        if source_valid is not None and np.shape(source_valid) != (cam_src.height, cam_src.width):
            raise ValueError(f"source_valid is {np.shape(source_valid)}, the camera's image "
                             f"{(cam_src.height, cam_src.width)}")
        self.cam_src, self.cam_dst, self.interpolation = cam_src, cam_dst, interpolation
        rays, valid = cam_dst.lens_normal_map() if target is None else target
        pos = np.where(valid[..., None], rays, 1.0).reshape(-1, 3)
        uv, seen = cam_src.sees(pos)
        self._uv, self._sees = np.nan_to_num(uv, nan=-1.0), seen & valid.ravel()
        self._valid = valid_pixels(cam_src) if source_valid is None else np.asarray(source_valid, bool)
        if interpolation == "nearest":  # the one pixel read must be valid
            idx, _ = nearest_entries(cam_src, self._uv, self._sees)
            self._sees &= self._valid.ravel()[idx[:, 0]]
        self._fast = Remap(cam_src, self._uv, self._sees, interpolation, self._valid)
        self._table = None

    def __repr__(self) -> str:
        return (f"Reimager({self.cam_src!r} -> {self.cam_dst!r}, interpolation="
                f"'{self.interpolation}', seen={int(self.seen.sum())})")

    @property
    def seen(self) -> np.ndarray:
        """``[H', W']`` bool: the target pixels some source pixel reaches."""
        return self._fast.reached.reshape(self.cam_dst.height, self.cam_dst.width)

    def part(self, keep: np.ndarray) -> Remap:
        """The ``cv2.remap`` path over the target pixels where ``keep`` (``[H' W']`` bool)
        alone: a rig's camera re-imaging its share of the pixels."""
        return self._fast.restricted(np.asarray(keep, bool).ravel())

    def _entries(self):
        """The exact table ``(idx [P, K], w [P, K])``, built on first use."""
        if self._table is None:
            entries = bilinear_entries if self.interpolation == "bilinear" else nearest_entries
            idx, w = entries(self.cam_src, self._uv, self._sees)
            self._table = idx, valid_entries(self.cam_src, idx, w, valid=self._valid)
        return self._table

    def __call__(self, image):
        """``image [H, W(, C)]`` (numpy or torch) -> ``[H', W'(, C)]`` of the same type;
        integer images keep their dtype (rounded)."""
        arr, is_np = _as_image(image, self.cam_src)
        if is_np and Remap.accepts(arr):
            out = self._fast(arr, keep_dtype=True)
        else:
            idx, w = self._entries()
            t = torch.as_tensor(arr)
            flat = (t if t.is_floating_point() else t.double()).reshape(-1, t.shape[-1])
            w = torch.as_tensor(w, dtype=flat.dtype)[..., None]
            out = torch.where(w > 0, flat[torch.as_tensor(idx)] * w, 0).sum(1)  # a left-out NaN stays out
            if not t.is_floating_point():
                info = torch.iinfo(t.dtype) if t.dtype != torch.bool else None
                out = out.round()
                out = (out.clamp(info.min, info.max) if info else out).to(t.dtype)
            out = out.numpy() if is_np else out
        out = out.reshape(self.cam_dst.height, self.cam_dst.width, -1)
        return out[..., 0] if np.ndim(image) == 2 else out


def render(image, cam_src: Camera, cam_dst: Camera, interpolation: str = "bilinear",
           source_valid: np.ndarray | None = None):
    """Re-image ``image`` taken by ``cam_src`` as ``cam_dst`` would see it, through the
    sphere: :class:`Reimager` for one image (build one to re-image many). Pixels the source
    does not see are 0. Returns numpy (or torch, for torch input) ``[H', W'(, C)]``."""
    return Reimager(cam_src, cam_dst, interpolation, source_valid)(image)


__all__ = ["Reimager", "render"]
