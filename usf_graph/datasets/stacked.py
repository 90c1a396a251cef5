"""What the datasets stored as one ``[S, ...]`` tensor per field share: PyG ``pre_transform``
on them, loading, reading a release's images, boxes, and the gravity of panoramas released
upright."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path

import torch
from torch_geometric.data import Data

from ..fileio import decode_image, load_refusal


def pre_transform_stacked(pre_transform: Callable[[Data], Data], samples: Iterable[Data],
                          field: str, fixed: tuple[str, ...] = ()) -> torch.Tensor:
    """Apply ``pre_transform`` to every sample and stack ``field`` back into ``[S, ...]``.

    A split is stored as one tensor, so the transform must keep ``field`` one shape for
    every sample, and may not change the ``fixed`` attributes (e.g. a grid's ``pos``
    shared by all samples): both would be lost in storage, so they raise instead.
    """
    out = []
    for i, d in enumerate(samples):
        before = {k: d[k].clone() for k in fixed}
        t = pre_transform(d)
        v = getattr(t, field, None) if t is not None else None
        if v is None:
            raise ValueError(f"pre_transform returned no '{field}' for sample {i}; it must "
                             f"return a Data with '{field}'")
        if out and v.shape != out[0].shape:
            raise ValueError(f"pre_transform changed the shape of '{field}' to {tuple(v.shape)} "
                             f"for sample {i} (sample 0: {tuple(out[0].shape)}); this dataset "
                             f"stores the split as one tensor, so every sample needs one shape")
        for k in fixed:
            if not torch.equal(t[k], before[k]):
                raise ValueError(f"pre_transform changed '{k}', which all samples share and "
                                 f"which is not stored per sample; use it as a transform instead")
        out.append(v)
    return torch.stack(out)


def load_or_rebuild(path, process: Callable[[], None], required: tuple[str, ...]) -> dict:
    """Load a processed file; one that cannot be read or lacks a ``required`` key is
    deleted and made again by ``process()`` (with a warning), never trusted."""
    import os
    import warnings

    try:
        blob = torch.load(path, weights_only=True)
        missing = set(required) - set(blob)
        if missing:
            raise KeyError(f"missing {sorted(missing)}")
    except Exception as e:  # noqa: BLE001 - whatever is wrong with the file, it is rebuilt
        warnings.warn(f"{path} is unreadable ({type(e).__name__}: {load_refusal(e)}); "
                      "processing it again", stacklevel=3)
        os.remove(path)
        process()
        blob = torch.load(path, weights_only=True)
    return blob


def read_release_image(path, flags, get_it: str):
    """An image of a dataset's release as OpenCV decodes it (``flags``); a missing file
    raises with ``get_it`` (where to get the data), one that does not decode names it."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing. " + get_it)
    img = decode_image(path, flags)
    if img is None:
        raise ValueError(f"{path} is not a readable PNG (corrupt or truncated); download it again")
    return img


def pack_boxes(boxes, classes) -> dict:
    """Per-sample boxes ``[K_i, 5]`` and classes ``[K_i]`` -> one ``boxes``, ``box_class``
    and ``box_ptr [S + 1]`` (sample i owns rows ``box_ptr[i]:box_ptr[i + 1]``)."""
    import numpy as np

    boxes = [np.reshape(b, (-1, 5)) for b in boxes]  # a single box may come as 5 numbers
    counts = [len(b) for b in boxes]
    return {"boxes": torch.as_tensor(np.concatenate(boxes)),
            "box_class": torch.as_tensor(np.concatenate([np.reshape(c, -1) for c in classes])).long(),
            "box_ptr": torch.as_tensor(np.r_[0, np.cumsum(counts)]).long()}


def add_boxes(data: Data, store, idx: int) -> Data:
    """Attach sample ``idx``'s ``boxes`` (float32) and ``box_class`` from ``store`` (an object
    with the fields of :func:`pack_boxes`) to ``data``."""
    a, b = int(store.box_ptr[idx]), int(store.box_ptr[idx + 1])
    data.boxes, data.box_class = store.boxes[a:b].float(), store.box_class[a:b]
    return data


def missing_release(dataset, get_it: str) -> FileNotFoundError:
    """The error for a dataset release not found under its ``raw_dir``: the files and
    folders it lacks (of ``raw_file_names``), then how to get it (``get_it``)."""
    root = Path(dataset.raw_dir)
    missing = [f for f in dataset.raw_file_names if not (root / f).exists()]
    return FileNotFoundError(f"{', '.join(missing)} not found under {root}. {get_it}")


class UprightAsReleased:
    """For datasets of panoramas released gravity-aligned (Stanford 2D-3D-S, PANDORA), whose
    split is ``self.x [S, ...]``."""

    @property
    def gravity(self) -> torch.Tensor:
        """``[S, 3]`` float64: +z for every panorama, gravity-aligned as released (the known
        up that ``usf-graph eval --known-up`` hands a model)."""
        return torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(len(self.x), 3)
