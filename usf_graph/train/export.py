"""A trained spherical segmenter bound to one camera, exported as one self-contained
program: ONNX (``.onnx``: onnxruntime, TensorRT, OpenVINO, C++) or ``torch.export``
(``.pt2``: ``torch.export.load``, AOTInductor). What ``usf-graph export`` runs.

The program takes the camera's image as it comes (``uint8 [H, W, 3]``, RGB) and, where
asked, gravity's up in the camera's sphere frame (``float32 [3]``, e.g. from an IMU), and
returns ``labels uint8 [H, W]`` (:data:`~usf_graph.train.apply.UNSEEN` where the camera
has no ray or its mask ignores the pixel) and the ``up [3]`` it read. Everything that
depends only on the camera and the grid is computed here once and held as constants: the
lifting table, the field of view, every layer's coefficients and the render table. So the
deployed program does per frame what :func:`~usf_graph.train.apply.segment_image` does,
and nothing else.

The layers take their plain forms (:mod:`usf_graph.tracing`): gathers into padded rows
and batched products instead of sparse tensors, which neither exporter can take. Export
checks the written program against :func:`~usf_graph.train.apply.segment_image` on a
procedural room rendered through the camera (:func:`check_exported`).
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..frontend import SphericalFrontend
from ..frontend.interpolation import valid_pixels
from ..sparse import padded_product, padded_rows, padded_values
from ..tracing import fixed_fields
from .apply import UNSEEN, choose_interpolation, input_grid, segment_image

#: What the exported files are: by their suffix.
FORMATS = {".onnx": "ONNX", ".pt2": "torch.export"}
#: ONNX opset of the files written (the exporter's default in torch 2.13).
OPSET = 18


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


class BoundSegmenter(nn.Module):
    r"""A spherical segmenter and one camera, as one module from image to labels.

    ``forward(image [H, W, 3] uint8[, up [3] float32])`` -> ``(labels [H, W] uint8, up
    [3] float32)``: the image in [0, 1] is lifted through the camera's table (``x_i =
    \sum_p T_{ip} I_p``), segmented on the grid with the camera's field of view, and each
    pixel takes the label of its nearest visible grid point. Where the given ``up`` is
    not finite or is zero, every label is :data:`UNSEEN` and the returned up is NaN: an
    exported program cannot raise, so it says so in its outputs.

    Args:
        model: a spherical segmenter (:class:`~usf_graph.models.SphericalUNet`,
            :class:`~usf_graph.models.SphericalDeepLabV3`), in evaluation mode here.
        camera: any :mod:`usf_graph.cameras` model (its mask and ``fov`` included).
        up: ``"input"`` (a second input), a fixed ``[3]`` vector, or ``None``: the
            model's own estimate (``.pt2`` only: ONNX has no eigendecomposition, which its
            polish needs).
        interpolation: as :func:`~usf_graph.train.apply.lift_for` (``auto`` picks
            ``area`` for images much finer than the grid).
    """

    def __init__(self, model: nn.Module, camera, up="input", interpolation: str = "auto"):
        super().__init__()
        grid = input_grid(model)
        # a model without gravity reads no up (it is isotropic): it takes the image alone
        self.up_mode = _up_mode(up) if getattr(model, "gravity", None) is not None else "none"
        if interpolation == "auto":
            interpolation = choose_interpolation(camera, grid)
        fe = SphericalFrontend(camera, grid, interpolation)
        self.camera, self.interpolation = camera, interpolation
        self.model = model.eval()
        self.size = (camera.height, camera.width)
        # the lift over the points with pixels only (a pinhole's table pads 16x otherwise),
        # then each point reads its row or a zero row at the end
        crow, col, val = fe.lift_table()
        counts = crow.long().diff()
        rows = torch.nonzero(counts > 0)[:, 0]  # every entry is in one of these, in order
        cols, slot = padded_rows(torch.cat([counts.new_zeros(1), counts[rows].cumsum(0)]), col)
        self.register_buffer("lift_col", cols)
        self.register_buffer("lift_w", padded_values(val.float(), slot))
        row_of = torch.full((len(counts),), len(rows), dtype=torch.int32)
        row_of[rows] = torch.arange(len(rows), dtype=torch.int32)
        self.register_buffer("lift_row", row_of)
        # None where the camera sees the whole sphere, as the models take it
        self.register_buffer("mask", None if bool(fe.mask.all()) else fe.mask.clone())
        crow, col, _ = fe.render_table("nearest")
        if not bool((crow.diff() == 1).all()):
            raise RuntimeError("the nearest render table must hold one point per pixel")
        self.register_buffer("nearest", col.int().clone())
        self.register_buffer("seen", torch.from_numpy(valid_pixels(camera).ravel().copy()))
        if isinstance(self.up_mode, torch.Tensor):
            self.register_buffer("fixed_up", self.up_mode[None].clone())

    def example(self) -> tuple:
        """Inputs of the right shapes and dtypes (a gray image, the up of a level camera)."""
        image = torch.full((*self.size, 3), 128, dtype=torch.uint8)
        return (image, torch.tensor([0.0, 0.0, 1.0])) if self.up_mode == "input" else (image,)

    def forward(self, image: torch.Tensor, up: torch.Tensor | None = None):
        rgb = image.reshape(-1, 3).float() / 255.0
        lifted = padded_product(self.lift_col, self.lift_w, rgb)  # [points with pixels, 3]
        x = torch.cat([lifted, lifted.new_zeros(1, 3)]).index_select(0, self.lift_row)[None]
        if self.up_mode == "none":
            logits = self.model(x, self.mask)
            u, ok = x.new_full((1, 3), math.nan), torch.ones((), dtype=torch.bool, device=x.device)
        elif self.up_mode is None:
            logits, grav = self.model(x, self.mask, return_gravity=True)
            u, ok = grav["up"], torch.ones((), dtype=torch.bool, device=x.device)
        else:
            u = self.fixed_up if up is None else up.reshape(1, 3).float()
            ok = torch.isfinite(u).all() & (u.norm() > 0)
            u = torch.where(ok, u, torch.tensor([[0.0, 0.0, 1.0]], device=x.device))
            u = u / u.norm()
            logits = self.model(x, self.mask, up=u)
        points = logits[0].argmax(-1)
        labels = torch.where(self.seen & ok, points.index_select(0, self.nearest), UNSEEN)
        labels = labels.to(torch.uint8)
        return labels.reshape(self.size), torch.where(ok, u[0], math.nan)


def _onnx_ready() -> None:
    try:
        import onnx  # noqa: F401
        import onnxscript  # noqa: F401
    except ImportError:
        raise ImportError("ONNX export needs onnx and onnxscript: pip install "
                          "'usf-graph[export]' (or export to .pt2)") from None


def export_segmenter(model: nn.Module, camera, path, up="input", interpolation: str = "auto",
                     check: bool = True, seed: int = 0) -> dict:
    """Write ``model`` bound to ``camera`` (:class:`BoundSegmenter`) to ``path``: ONNX for
    ``.onnx``, ``torch.export`` for ``.pt2``; then, with ``check``, run the written file
    on a procedural room rendered through the camera (room ``seed``) and compare with
    :func:`~usf_graph.train.apply.segment_image` (:func:`check_exported`). Returns what
    it did: the file, its format and size, the seconds taken and the check's numbers."""
    path = Path(path)
    fmt = FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise ValueError(f"{path}: name the file .onnx (ONNX) or .pt2 (torch.export)")
    if fmt == "ONNX":
        _onnx_ready()
        if up is None:
            raise ValueError("an ONNX program cannot hold the up estimate (ONNX has no "
                             "eigendecomposition, which its polish needs): export with "
                             "up='input' (--up-input: an IMU) or a fixed up (--up X Y Z), "
                             "or to .pt2")
    t0 = time.perf_counter()
    bound = BoundSegmenter(model, camera, up, interpolation).eval()
    example = bound.example()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.part{path.suffix}")
    with torch.no_grad():
        with fixed_fields() as fields:  # builds the plain forms' tables, records the masks
            bound(*example)
        with fixed_fields(fields):
            if fmt == "ONNX":
                names = ["image", "up"][:len(example)]
                program = torch.onnx.export(bound, example, dynamo=True, opset_version=OPSET,
                                            input_names=names, output_names=["labels", "up_read"],
                                            verbose=False)
                program.save(str(tmp))
            else:
                torch.export.save(torch.export.export(bound, example), str(tmp))
    tmp.replace(path)  # atomic: a failed export leaves no half-written file
    info = {"path": str(path), "format": fmt, "bytes": path.stat().st_size,
            "inputs": ["image uint8 [H, W, 3] RGB"] + (["up float32 [3]"] if len(example) > 1 else []),
            "size": list(bound.size), "interpolation": bound.interpolation,
            "export_s": time.perf_counter() - t0}
    if check:
        reads = None if bound.up_mode == "none" else up  # an isotropic model reads no up
        info["check"] = check_exported(path, model, camera, reads, bound.interpolation, seed)
    return info


def load_exported(path, threads: int | None = None):
    """An exported file as a function ``(image uint8 [H, W, 3], up [3] or None) ->
    (labels [H, W] uint8, up [3])`` on numpy arrays: ONNX files run in onnxruntime (on
    ``threads`` CPU threads; None: its default), ``.pt2`` files through
    ``torch.export.load`` (on torch's threads). Load once, call per frame."""
    path = Path(path)
    if path.suffix.lower() == ".onnx":
        try:
            import onnxruntime as ort
        except ImportError:
            raise ImportError("running an ONNX file needs onnxruntime: pip install "
                              "'usf-graph[export]'") from None
        options = ort.SessionOptions()
        if threads:
            options.intra_op_num_threads = int(threads)
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        names = [i.name for i in session.get_inputs()]

        def run(image, up=None):
            feeds = _feeds(image, up, len(names), path)
            labels, u = session.run(None, dict(zip(names, feeds)))
            return labels, u
        return run
    program = torch.export.load(str(path)).module()
    takes = len(program.graph.find_nodes(op="placeholder")) if hasattr(program, "graph") else None

    def run(image, up=None):
        feeds = _feeds(image, up, takes, path)
        with torch.no_grad():
            labels, u = program(*(torch.from_numpy(f) for f in feeds))
        return labels.numpy(), u.numpy()
    return run


def _feeds(image, up, takes: int | None, path) -> list:
    feeds = [np.ascontiguousarray(image, np.uint8)]
    if up is not None:
        feeds.append(np.asarray(up, np.float32).reshape(3))
    if takes is not None and takes != len(feeds):
        raise ValueError(f"{path} takes {'an image and up' if takes == 2 else 'an image alone'}; "
                         f"give up exactly when it takes one")
    return feeds


def check_exported(path, model: nn.Module, camera, up, interpolation: str, seed: int = 0) -> dict:
    """The exported file against :func:`~usf_graph.train.apply.segment_image` on room
    ``seed`` rendered through ``camera``: the share of the camera's pixels where both give
    the same label (argmax ties and float32 summation order can flip a few), the largest
    angle between their ups (degrees), and the program's time per frame.

    Raises ``RuntimeError`` when fewer than 99% of the pixels agree: the file would be a
    silent wrong answer."""
    from ..scenes import make_room
    from ..scenes.render import render

    view = render(make_room(seed), camera, boxes=False)
    given = None if up is None else [0.0, 0.0, 1.0] if up == "input" else up
    ref = segment_image(model, view.rgb, camera, up=given, interpolation=interpolation)
    feed_up = [0.0, 0.0, 1.0] if up == "input" else None
    t0 = time.perf_counter()
    run = load_exported(path)
    load = time.perf_counter() - t0
    labels, u = run(view.rgb, feed_up)
    t0 = time.perf_counter()
    run(view.rgb, feed_up)
    seen = ref["labels"] != UNSEEN
    agree = float((labels[seen] == ref["labels"][seen]).mean()) if seen.any() else 1.0
    same_unseen = bool(((labels == UNSEEN) == ~seen).all())
    a, b = np.asarray(u, np.float64), np.asarray(ref["up"] if ref["up"] is not None else u, np.float64)
    angle = math.atan2(np.linalg.norm(np.cross(a, b)), float(np.dot(a, b))) if np.isfinite(a).all() else 0.0
    out = {"room": seed, "pixels_seen": int(seen.sum()), "agree": agree,
           "unseen_match": same_unseen, "up_angle_deg": math.degrees(angle),
           "load_s": load, "frame_s": time.perf_counter() - t0}
    if agree < 0.99 or not same_unseen:
        raise RuntimeError(f"the exported {path} disagrees with usf-graph on a rendered room: "
                           f"{100 * agree:.2f}% of the pixels agree, unseen pixels "
                           f"{'match' if same_unseen else 'differ'}. Please report it with "
                           "the checkpoint and the calibration")
    return out


__all__ = ["BoundSegmenter", "FORMATS", "check_exported", "export_segmenter", "load_exported"]
