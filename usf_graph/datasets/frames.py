"""What the datasets of a recording's frames share (a ROS bag's, a video's): every frame
lifted once, only the signal stored, and one grid and field of view for all."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import torch
from torch_geometric.data import Dataset

from ..fileio import atomic_torch_save
from ..frontend.image import SphericalImage
from .stacked import load_or_rebuild, pre_transform_stacked


def digest(key: dict) -> str:
    """16 hex digits of a JSON-able description of everything a processed file depends on."""
    return hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:16]


class LiftedFrames(Dataset):
    """A recording's frames lifted onto :attr:`grid` by :attr:`frontend` (a
    :class:`~usf_graph.frontend.SphericalFrontend` or
    :class:`~usf_graph.frontend.RigFrontend`), stored as one float16 tensor ``x [S, N, C]``
    with each frame's ``stamp_ns`` and the subclass's own fields. A subclass sets ``grid``
    ``frontend`` and :attr:`source` (the recording, read where it is), names its processed
    file, and makes it with :meth:`store`."""

    #: the fields of the processed file besides ``x`` and ``stamp_ns``
    extra_fields: tuple[str, ...] = ()
    source: Path

    @property
    def raw_dir(self) -> str:
        """The folder that holds the recording."""
        return str(self.source.parent)

    @property
    def raw_file_names(self):
        return [self.source.name]

    def download(self):
        raise FileNotFoundError(f"{self.source} does not exist")

    def _load(self) -> dict:
        blob = load_or_rebuild(self.processed_paths[0], self.process,
                               ("x", "stamp_ns", *self.extra_fields))
        self.x, self.stamp_ns = blob["x"], blob["stamp_ns"]
        return blob

    def store(self, xs: list, stamps: list, **extra) -> None:
        """Writes the lifted frames (``xs``: ``[N, C]`` each), after ``pre_transform``."""
        x = torch.stack(xs)
        if self.pre_transform is not None:
            x = pre_transform_stacked(self.pre_transform, (self._sample(xi) for xi in x), "x",
                                      fixed=("pos",))
        atomic_torch_save({"x": x.to(torch.float16), "stamp_ns": torch.as_tensor(stamps, dtype=torch.int64),
                           **extra}, self.processed_paths[0])

    def len(self) -> int:
        return len(self.x)

    def _sample(self, x) -> SphericalImage:
        return SphericalImage(x=x, pos=self.grid.pos.float(), area=self.grid.area.float())

    def get(self, idx: int) -> SphericalImage:
        d = self._sample(self.x[idx].float())
        d.mask = self.frontend.mask.clone()
        d.stamp_ns = self.stamp_ns[idx].reshape(1)
        return d


__all__ = ["LiftedFrames", "digest"]
