"""Lifted samples on disk: the signal, the mask and the geometry's specification, not the graph.

A file is a ``torch.save`` of plain data (tensors, numbers, strings), read back with
``torch.load(..., weights_only=True)``. :func:`load_lifted` rebuilds the
:class:`SphericalImage` with the grid and its radius graph from the geometry cache, so a
sample on disk costs its signal: 0.5 MB for RGB on ``icosahedral:6`` instead of 7 MB.
"""

from __future__ import annotations

from pathlib import Path

import torch

from ..fileio import atomic_write, load_refusal
from ..grids import from_spec
from .frontend import grid_graph
from .image import SphericalImage

FORMAT = "usf_graph.lifted"
VERSION = 1


def save_lifted(path, x: torch.Tensor, frontend, mask: torch.Tensor | None = None,
                source: str | None = None) -> None:
    """Write lifted values ``x [N, C]`` from ``frontend`` (a :class:`SphericalFrontend` or
    :class:`RigFrontend`) to ``path`` atomically. ``source``: the image it came from."""
    mask = frontend.mask if mask is None else mask
    if x.shape[0] != len(frontend.grid) or mask.shape != (len(frontend.grid),):
        raise ValueError(f"x {tuple(x.shape)} and mask {tuple(mask.shape)} do not fit the grid "
                         f"{frontend.grid.spec} of {len(frontend.grid)} points")
    fes = frontend.frontends if hasattr(frontend, "frontends") else [frontend]
    names = getattr(frontend, "names", ["cam0"])
    blob = {"format": FORMAT, "version": VERSION, "x": x.detach().cpu(), "mask": mask.cpu(),
            "grid": frontend.grid.spec, "radius": fes[0].radius,
            "interpolation": fes[0].interpolation, "blend": getattr(frontend, "blend", None),
            "cameras": {n: fe.camera.to_doc() for n, fe in zip(names, fes)},
            "source": None if source is None else str(source)}
    atomic_write(path, lambda f: torch.save(blob, f))


def read_lifted(path) -> dict:
    """The plain contents of a lifted file, checked (see :func:`save_lifted`)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"lifted file {path} does not exist")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - a truncated or foreign file fails in many ways
        raise ValueError(f"{path}: not a readable lifted file ({type(e).__name__}: {load_refusal(e)}); "
                         "write it again with `usf-graph lift --out`") from e
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        raise ValueError(f"{path}: not a usf-graph lifted file (no format '{FORMAT}')")
    if blob.get("version") != VERSION:
        raise ValueError(f"{path}: lifted file version {blob.get('version')}, this usf-graph "
                         f"reads version {VERSION}; lift the image again")
    for k in ("x", "mask", "grid", "radius"):
        if k not in blob:
            raise ValueError(f"{path}: lifted file lacks '{k}'; lift the image again")
    return blob


def load_lifted(path, cache=None) -> SphericalImage:
    """A lifted file (``usf-graph lift --out``, :func:`save_lifted`) as a
    :class:`SphericalImage`; the grid and radius graph come from the geometry cache."""
    blob = read_lifted(path)
    grid = from_spec(blob["grid"])
    x, mask = blob["x"], blob["mask"].bool()
    if x.shape[0] != len(grid) or mask.shape != (len(grid),):
        raise ValueError(f"{path}: x {tuple(x.shape)} and mask {tuple(mask.shape)} do not fit "
                         f"the grid {blob['grid']} of {len(grid)} points; the file is corrupt")
    return SphericalImage.on_grid(x, grid, mask, *grid_graph(grid, float(blob["radius"]), cache))


