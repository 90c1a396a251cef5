"""What a detector is scored on: a rooms split's views with their boxes, in the form a
spherical detector (its grid) or the planar one (panoramas) reads them
(:class:`DetectionSet`), and which true boxes a camera sees."""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import Dataset
from tqdm.auto import tqdm

from ..cameras import Equirectangular
from ..frontend import render
from ..ops import share_in_view
from .det_metrics import FULLY_SEEN


class DetectionSet(Dataset):
    """A split's detector inputs and boxes, batched by :meth:`collate`.

    ``x``: ``[S, N, C]`` spherical signals or ``[S, H, W, 3]`` uint8 images (made
    ``[B, 3, H, W]`` in [0, 1] per batch); ``mask``: the field of view shared by all
    samples (``[N]`` or ``[H, W]``; ``None``: everything seen); boxes as
    :func:`~usf_graph.datasets.stacked.pack_boxes` stores them; ``seen [K]``: the share of
    each box in the camera's field of view (``None``: all of every box), which decides the
    boxes :meth:`ignored` in scoring.
    """

    def __init__(self, x, boxes, box_class, box_ptr, mask=None, seen=None):
        self.x, self.mask = x, mask
        self.boxes, self.box_class, self.box_ptr = boxes.double(), box_class.long(), box_ptr.long()
        if len(box_ptr) != len(x) + 1:
            raise ValueError(f"box_ptr has {len(box_ptr)} entries for {len(x)} samples")
        if seen is not None and len(seen) != len(boxes):
            raise ValueError(f"seen has {len(seen)} entries for {len(boxes)} boxes")
        self.seen = None if seen is None else np.asarray(seen, np.float64)

    @classmethod
    def spherical(cls, ds) -> DetectionSet:
        """From a :class:`~usf_graph.datasets.RoomsDetection` (or any split with ``x``,
        ``mask`` and packed boxes): the lifted signals."""
        mask = getattr(ds, "mask", None)
        if mask is not None and mask.dim() == 2:
            if not (mask == mask[0]).all():
                raise ValueError("the samples have different fields of view; a batch shares one mask")
            mask = mask[0]
        part = mask is not None and not mask.all()
        return cls(ds.x, ds.boxes, ds.box_class, ds.box_ptr, mask if part else None,
                   boxes_seen(ds) if part else None)

    @classmethod
    def planar(cls, ds, width: int, height: int, progress: bool = True) -> DetectionSet:
        """The split's images as ``width x height`` panoramas: as they are when the camera is
        that panorama, re-imaged through the sphere otherwise."""
        pano = Equirectangular(width, height)
        cam = ds.camera
        if cam.key() == pano.key():
            return cls(ds.image, ds.boxes, ds.box_class, ds.box_ptr)
        imgs = np.stack([render(im.numpy(), cam, pano) for im in tqdm(
            ds.image, desc="re-imaging as panoramas", leave=False, disable=not progress)])
        _, seen = cam.sees(pano.lens_normal_map()[0].reshape(-1, 3))
        return cls(torch.as_tensor(imgs), ds.boxes, ds.box_class, ds.box_ptr,
                   torch.as_tensor(seen.reshape(height, width)), None if seen.all() else boxes_seen(ds))

    def first(self, n: int) -> DetectionSet:
        """The first ``n`` samples (all when there are fewer)."""
        n = min(n, len(self.x))
        end = int(self.box_ptr[n])
        return DetectionSet(self.x[:n], self.boxes[:end], self.box_class[:end],
                            self.box_ptr[: n + 1], self.mask, None if self.seen is None else self.seen[:end])

    def __len__(self) -> int:
        return len(self.x)

    def __getitem__(self, i: int) -> int:
        return i

    def truth(self, i: int):
        a, b = int(self.box_ptr[i]), int(self.box_ptr[i + 1])
        return self.boxes[a:b].numpy(), self.box_class[a:b].numpy()

    def ignored(self, i: int | None = None) -> np.ndarray:
        """Bool ``[G]``: the true boxes of sample ``i`` (``None``: of all samples) that the
        camera sees less than :data:`~usf_graph.train.det_metrics.FULLY_SEEN` of, ignored
        in scoring."""
        a, b = (0, len(self.boxes)) if i is None else (int(self.box_ptr[i]), int(self.box_ptr[i + 1]))
        return np.zeros(b - a, bool) if self.seen is None else self.seen[a:b] < FULLY_SEEN

    def describe_ignored(self) -> str:
        """How many true boxes there are, and how many of them are ignored."""
        return (f"{len(self.boxes)} true boxes, {int(self.ignored().sum())} of them ignored (the "
                f"camera sees less than {FULLY_SEEN:.0%} of them)")

    def collate(self, idx: list[int]):
        """Indices -> ``(x, mask, boxes [K, 5], classes [K], image [K])``."""
        idx = torch.as_tensor(idx, dtype=torch.long)  # an empty list too
        x = self.x[idx]
        x = x.permute(0, 3, 1, 2).float() / 255 if x.dtype == torch.uint8 else x.float()
        a, b = self.box_ptr[idx], self.box_ptr[idx + 1]
        rows = torch.cat([torch.arange(int(s), int(e)) for s, e in zip(a, b)]) if len(idx) else \
            torch.zeros(0, dtype=torch.long)
        image = torch.repeat_interleave(torch.arange(len(idx)), b - a)
        return x, self.mask, self.boxes[rows].float(), self.box_class[rows], image


def boxes_seen(ds) -> np.ndarray:
    """The share of each of a split's boxes (``ds.boxes``, in the view's frame) that its
    camera ``ds.camera`` sees (:func:`~usf_graph.ops.share_in_view`)."""
    if getattr(ds, "camera", None) is None:
        raise ValueError(f"{type(ds).__name__} sees part of the sphere but has no camera to tell "
                         "which share of each box it sees; give it a 'camera' attribute")
    return share_in_view(ds.boxes.numpy(), lambda d: ds.camera.sees(d)[1])
