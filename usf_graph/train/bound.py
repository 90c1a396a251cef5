"""Trained spherical models bound to one camera (or one rig): modules from the camera's
``uint8`` images to its answers, every piece of geometry held as a constant, which
:mod:`usf_graph.train.export` writes as one program.

:class:`BoundSegmenter` answers with a label image per camera, :class:`BoundDetector`
with spherical boxes. Both lift the images through the cameras' tables
(:class:`CameraIO`) and read gravity's up as given (an input, or fixed) or from the
model's own estimate; an exported program cannot raise, so a bad up is reported in the
outputs instead.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import torch
from torch import nn

from ..frontend import RigFrontend, SphericalFrontend
from ..frontend.interpolation import valid_pixels
from ..sparse import entry_rows, padded_product, padded_rows, padded_values, row_pointers
from .apply import UNSEEN, auto_interpolation, cameras_of, input_grid, is_rig


def _up_mode(up):
    """``"input"``, ``None`` (the model's estimate) or a unit ``[3]`` vector (a camera
    mounted at a fixed angle to gravity)."""
    if up is None or (isinstance(up, str) and up == "input"):
        return up
    u = np.asarray(up, np.float64).reshape(-1)
    if u.shape != (3,) or not np.isfinite(u).all() or np.linalg.norm(u) < 1e-9:
        raise ValueError(f"up must be 'input', None (the model's estimate) or 3 finite numbers, "
                         f"not all 0 (x forward, y left, z up), got {up!r}")
    return torch.from_numpy(u / np.linalg.norm(u)).float()


class CameraIO(nn.Module):
    """One camera's part of a bound program: its lifting table, weighted by its share of
    each point (a rig's blend; 1 for one camera) and kept over the points it lifts only (a
    pinhole's table would pad 16x otherwise), and, with ``render``, its nearest-point
    render table (a segmenter's labels go back to the pixels; a detector's boxes do not)."""

    def __init__(self, fe: SphericalFrontend, share: torch.Tensor | None = None, render: bool = True):
        super().__init__()
        cam = fe.camera
        self.size, self.camera_key = (cam.height, cam.width), cam.key()
        crow, col, val = fe.lift_table()
        counts = crow.long().diff()
        if share is not None:  # a rig: each entry weighted by its point's share, zeros dropped
            row = entry_rows(counts)
            w = share.to(val.dtype)[row]
            keep = w > 0
            col, val = col[keep], val[keep] * w[keep]
            counts = torch.bincount(row[keep], minlength=len(counts))
        rows = torch.nonzero(counts > 0)[:, 0]  # every entry is in one of these, in order
        cols, slot = padded_rows(row_pointers(counts[rows]), col)
        self.register_buffer("lift_col", cols)
        self.register_buffer("lift_w", padded_values(val.float(), slot))
        row_of = torch.full((len(counts),), len(rows), dtype=torch.int32)
        row_of[rows] = torch.arange(len(rows), dtype=torch.int32)
        self.register_buffer("lift_row", row_of)  # each point's row, or the zero row past the end
        if not render:
            return
        crow, col, _ = fe.render_table("nearest")
        if not bool((crow.diff() == 1).all()):
            raise RuntimeError("the nearest render table must hold one point per pixel")
        seen = torch.from_numpy(valid_pixels(cam).ravel().copy())
        # each pixel's point, or N (past the points: the unseen label) where it has no ray
        self.register_buffer("nearest", torch.where(seen, col, len(counts)).int())

    def lift(self, image: torch.Tensor) -> torch.Tensor:
        """``uint8 [H, W, 3]`` -> ``[N, 3]`` in [0, 1], 0 where the camera adds nothing (the
        pixels gathered as bytes, then converted)."""
        lifted = padded_product(self.lift_col, self.lift_w, image.reshape(-1, 3)) / 255.0
        return torch.cat([lifted, lifted.new_zeros(1, 3)]).index_select(0, self.lift_row)

    def labels(self, points: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
        """Per-point labels ``[N]`` -> ``uint8 [H, W]``, :data:`UNSEEN` where the camera has
        no ray or ``ok`` is False: one gather of bytes from the points' labels and the
        unseen one after them."""
        table = torch.where(ok, points, UNSEEN).to(torch.uint8)
        table = torch.cat([table, table.new_full((1,), UNSEEN)])
        return table.index_select(0, self.nearest).reshape(self.size)


class BoundModel(nn.Module):
    r"""A spherical model and one camera (or one rig): what :class:`BoundSegmenter` and
    :class:`BoundDetector` share. ``forward(image [H, W, 3] uint8, ...[, up [3]
    float32])``: the images in [0, 1] are lifted through the cameras' tables (``x_i =
    \sum_c \sum_p w_{ci} T^c_{ip} I^c_p``, a rig's blend weights :math:`w_{ci}` as
    :class:`~usf_graph.frontend.RigFrontend` makes them) and the model runs on the grid
    with the joint field of view. Where the given ``up`` is not finite or is zero, the
    answers say "nothing" and the returned up is NaN: an exported program cannot raise,
    so it says so in its outputs.

    Args:
        model: a spherical model with an ``input_grid`` (in evaluation mode here).
        camera: any :mod:`usf_graph.cameras` model (its mask and ``fov`` included), or a
            rig: a list or ``{name: camera}`` of cameras mounted by their ``rotation``
            (:func:`usf_graph.cameras.load_rig`), one image each, in that order.
        up: ``"input"`` (the last input), a fixed ``[3]`` vector, or ``None``: the model's
            own estimate (its polish's eigendecompositions by Jacobi rotations,
            :func:`~usf_graph.models.gravity.symmetric_eigh3`, since ONNX has no
            eigendecomposition). A model without gravity reads no up and takes the images
            alone.
        interpolation: as :func:`~usf_graph.train.apply.lift_for` (``auto`` picks
            ``area`` for images much finer than the grid, for a rig if any camera needs it).
    """

    task = ""

    def __init__(self, model: nn.Module, camera, up="input", interpolation: str = "auto"):
        super().__init__()
        grid = input_grid(model)
        self.up_mode = _up_mode(up) if getattr(model, "gravity", None) is not None else "none"
        cams = cameras_of(camera)
        self.names = list(camera) if isinstance(camera, Mapping) else \
            [f"cam{i}" for i in range(len(cams))] if is_rig(camera) else ["image"]
        if interpolation == "auto":
            interpolation = auto_interpolation(cams, grid)
        self.interpolation = interpolation
        self.model = model.eval()
        if is_rig(camera):
            rig = RigFrontend(camera, grid, interpolation=interpolation)
            fes, shares, mask = rig.frontends, list(rig.weights), rig.mask
        else:
            fe = SphericalFrontend(camera, grid, interpolation)
            fes, shares, mask = [fe], [None], fe.mask
        self.cameras = nn.ModuleList(CameraIO(f, w, render=self.task == "seg") for f, w in zip(fes, shares))
        # None where the cameras see the whole sphere, as the models take it
        self.register_buffer("mask", None if bool(mask.all()) else mask.clone())
        if isinstance(self.up_mode, torch.Tensor):
            self.register_buffer("fixed_up", self.up_mode[None].clone())

    @property
    def input_names(self) -> list[str]:
        return self.names + (["up"] if self.up_mode == "input" else [])

    def example(self) -> tuple:
        """Inputs of the right shapes and dtypes (gray images, the up of a level camera)."""
        images = tuple(torch.full((*c.size, 3), 128, dtype=torch.uint8) for c in self.cameras)
        return images + ((torch.tensor([0.0, 0.0, 1.0]),) if self.up_mode == "input" else ())

    def _model(self, x: torch.Tensor, up: torch.Tensor | None):
        """The model on ``x [1, N, 3]`` given ``up [1, 3]`` (None: it reads none)."""
        raise NotImplementedError

    def _estimate(self, x: torch.Tensor):
        """The model on ``x`` with its own up estimate: ``(its output, up [1, 3])``."""
        raise NotImplementedError

    def _run(self, inputs: tuple):
        """The model on the lifted images: ``(its output, up [1, 3], ok)``, ``ok`` a bool
        scalar, False where the given up is unusable (the up then NaN)."""
        k = len(self.cameras)
        x = sum(c.lift(im) for c, im in zip(self.cameras, inputs[:k]))[None]  # [1, N, 3]
        ok = torch.ones((), dtype=torch.bool, device=x.device)
        if self.up_mode == "none":
            return self._model(x, None), x.new_full((1, 3), math.nan), ok
        if self.up_mode is None:
            out, u = self._estimate(x)
            return out, u, ok
        u = inputs[k].reshape(1, 3).float() if self.up_mode == "input" else self.fixed_up
        ok = torch.isfinite(u).all() & (u.norm() > 0)
        u = torch.where(ok, u, torch.tensor([[0.0, 0.0, 1.0]], device=x.device))
        u = u / u.norm()
        return self._model(x, u), torch.where(ok, u, math.nan), ok


class BoundSegmenter(BoundModel):
    """A spherical segmenter and one camera (or rig), as one module from images to labels
    (:class:`BoundModel`): ``forward(image [H, W, 3] uint8, ...[, up [3] float32])`` ->
    ``(labels [H, W] uint8, ..., up [3] float32)``, one label image per camera, each pixel
    the label of its camera's nearest visible grid point (:data:`UNSEEN` where the camera
    has no ray, and everywhere where the given up is unusable). ``model``: a
    :class:`~usf_graph.models.SphericalUNet` or :class:`~usf_graph.models.SphericalDeepLabV3`.
    """

    task = "seg"

    @property
    def output_names(self) -> list[str]:
        return (["labels"] if self.names == ["image"] else [f"labels_{n}" for n in self.names]) \
            + ["up_read"]

    def _model(self, x, up):
        return self.model(x, self.mask) if up is None else self.model(x, self.mask, up=up)

    def _estimate(self, x):
        logits, grav = self.model(x, self.mask, return_gravity=True)
        return logits, grav["up"]

    def forward(self, *inputs: torch.Tensor):
        logits, u, ok = self._run(inputs)
        points = logits[0].argmax(-1)
        return (*(c.labels(points, ok) for c in self.cameras), u[0])


class BoundDetector(BoundModel):
    """A spherical detector and one camera (or rig), as one module from images to boxes
    (:class:`BoundModel`): ``forward(image [H, W, 3] uint8, ...[, up [3] float32])`` ->
    ``(boxes [k, 5] float32, classes [k] int64, scores [k] float32, up [3] float32)``, as
    :func:`~usf_graph.train.apply.detect_image` decodes them
    (:meth:`~usf_graph.models.SphericalDetector.decode_image`, here in float32): boxes in
    radians ``[lon, lat, fov_x, fov_y, roll]`` in the camera's sphere frame (a rig's first
    camera's; :mod:`usf_graph.ops.boxes`), best first. The detections are the rows whose
    score is above 0; the others score 0 (all of them where the given up is unusable).
    ``k``, ``threshold``, ``nms`` and ``drop_hidden`` as
    :meth:`~usf_graph.models.SphericalDetector.decode_image`'s.
    """

    task = "det"

    def __init__(self, model: nn.Module, camera, up="input", interpolation: str = "auto",
                 k: int = 100, threshold: float = 0.05, nms: float | None = 0.5,
                 drop_hidden: bool = True):
        if not hasattr(model, "decode_image"):  # before the camera's tables are built
            raise ValueError(f"{type(model).__name__} is not a spherical detector")
        super().__init__(model, camera, up, interpolation)
        self.decoding = dict(k=int(k), threshold=float(threshold),
                             nms=None if nms is None else float(nms), drop_hidden=bool(drop_hidden))

    @property
    def output_names(self) -> list[str]:
        return ["boxes", "classes", "scores", "up_read"]

    def _model(self, x, up):
        return self.model(x, self.mask, up=up)

    def _estimate(self, x):
        out = self.model(x, self.mask)
        return out, out["gravity"]["up"]

    def forward(self, *inputs: torch.Tensor):
        out, u, ok = self._run(inputs)
        boxes, cls, score, kept = self.model.decode_image(out, 0, **self.decoding)
        score = torch.where(kept & ok, score, torch.zeros_like(score))
        return boxes, cls, score, u[0]


__all__ = ["BoundDetector", "BoundModel", "BoundSegmenter", "CameraIO"]
