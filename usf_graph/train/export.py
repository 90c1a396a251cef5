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

import contextlib
import json
import logging
import math
import time
import warnings
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..frontend import RigFrontend, SphericalFrontend
from ..frontend.interpolation import valid_pixels
from ..sparse import entry_rows, padded_product, padded_rows, padded_values
from ..tracing import fixed_fields
from .apply import (
    UNSEEN,
    auto_interpolation,
    cameras_of,
    class_names,
    input_grid,
    is_rig,
    segment_image,
)

#: What the exported files are: by their suffix.
FORMATS = {".onnx": "ONNX", ".pt2": "torch.export"}
#: ONNX opset of the files written (the exporter's default in torch 2.13).
OPSET = 18
#: An up estimate's margin under which its best two candidates tie (float32 summation
#: order then picks either): the check compares the rest given the program's up.
TIE_MARGIN = 1e-3
#: The ``.pt2`` archive's extra file that holds :func:`metadata`.
META_FILE = "usf_graph.json"


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
    pinhole's table would pad 16x otherwise), and its nearest-point render table."""

    def __init__(self, fe: SphericalFrontend, share: torch.Tensor | None = None):
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
        cols, slot = padded_rows(torch.cat([counts.new_zeros(1), counts[rows].cumsum(0)]), col)
        self.register_buffer("lift_col", cols)
        self.register_buffer("lift_w", padded_values(val.float(), slot))
        row_of = torch.full((len(counts),), len(rows), dtype=torch.int32)
        row_of[rows] = torch.arange(len(rows), dtype=torch.int32)
        self.register_buffer("lift_row", row_of)  # each point's row, or the zero row past the end
        crow, col, _ = fe.render_table("nearest")
        if not bool((crow.diff() == 1).all()):
            raise RuntimeError("the nearest render table must hold one point per pixel")
        self.register_buffer("nearest", col.int().clone())
        self.register_buffer("seen", torch.from_numpy(valid_pixels(cam).ravel().copy()))

    def lift(self, image: torch.Tensor) -> torch.Tensor:
        """``uint8 [H, W, 3]`` -> ``[N, 3]`` in [0, 1], 0 where the camera adds nothing."""
        rgb = image.reshape(-1, 3).float() / 255.0
        lifted = padded_product(self.lift_col, self.lift_w, rgb)
        return torch.cat([lifted, lifted.new_zeros(1, 3)]).index_select(0, self.lift_row)

    def labels(self, points: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
        """Per-point labels ``[N]`` -> ``uint8 [H, W]``, :data:`UNSEEN` where the camera has
        no ray or ``ok`` is False."""
        out = torch.where(self.seen & ok, points.index_select(0, self.nearest), UNSEEN)
        return out.to(torch.uint8).reshape(self.size)


class BoundSegmenter(nn.Module):
    r"""A spherical segmenter and one camera (or one rig), as one module from images to
    labels.

    ``forward(image [H, W, 3] uint8, ...[, up [3] float32])`` -> ``(labels [H, W] uint8,
    ..., up [3] float32)``, one image and one label image per camera: the images in [0,
    1] are lifted through the cameras' tables (``x_i = \sum_c \sum_p w_{ci} T^c_{ip}
    I^c_p``, a rig's blend weights :math:`w_{ci}` as :class:`~usf_graph.frontend.
    RigFrontend` makes them), segmented on the grid with the joint field of view, and each
    pixel takes the label of its camera's nearest visible grid point. Where the given
    ``up`` is not finite or is zero, every label is :data:`UNSEEN` and the returned up is
    NaN: an exported program cannot raise, so it says so in its outputs.

    Args:
        model: a spherical segmenter (:class:`~usf_graph.models.SphericalUNet`,
            :class:`~usf_graph.models.SphericalDeepLabV3`), in evaluation mode here.
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
        self.cameras = nn.ModuleList(CameraIO(f, w) for f, w in zip(fes, shares))
        # None where the cameras see the whole sphere, as the models take it
        self.register_buffer("mask", None if bool(mask.all()) else mask.clone())
        if isinstance(self.up_mode, torch.Tensor):
            self.register_buffer("fixed_up", self.up_mode[None].clone())

    @property
    def input_names(self) -> list[str]:
        return self.names + (["up"] if self.up_mode == "input" else [])

    @property
    def output_names(self) -> list[str]:
        return (["labels"] if self.names == ["image"] else [f"labels_{n}" for n in self.names]) \
            + ["up_read"]

    def example(self) -> tuple:
        """Inputs of the right shapes and dtypes (gray images, the up of a level camera)."""
        images = tuple(torch.full((*c.size, 3), 128, dtype=torch.uint8) for c in self.cameras)
        return images + ((torch.tensor([0.0, 0.0, 1.0]),) if self.up_mode == "input" else ())

    def forward(self, *inputs: torch.Tensor):
        k = len(self.cameras)
        x = sum(c.lift(im) for c, im in zip(self.cameras, inputs[:k]))[None]  # [1, N, 3]
        true = torch.ones((), dtype=torch.bool, device=x.device)
        if self.up_mode == "none":
            logits, u, ok = self.model(x, self.mask), x.new_full((1, 3), math.nan), true
        elif self.up_mode is None:
            logits, grav = self.model(x, self.mask, return_gravity=True)
            u, ok = grav["up"], true
        else:
            u = inputs[k].reshape(1, 3).float() if self.up_mode == "input" else self.fixed_up
            ok = torch.isfinite(u).all() & (u.norm() > 0)
            u = torch.where(ok, u, torch.tensor([[0.0, 0.0, 1.0]], device=x.device))
            u = u / u.norm()
            logits = self.model(x, self.mask, up=u)
        points = logits[0].argmax(-1)
        return (*(c.labels(points, ok) for c in self.cameras), torch.where(ok, u[0], math.nan))


def _onnx_ready() -> None:
    try:
        import onnx  # noqa: F401
        import onnxscript  # noqa: F401
    except ImportError:
        raise ImportError("ONNX export needs onnx and onnxscript: pip install "
                          "'usf-graph[export]' (or export to .pt2)") from None


def metadata(bound: BoundSegmenter) -> dict[str, str]:
    """What an exported file says of itself (ONNX ``metadata_props``, a ``.pt2``'s
    :data:`META_FILE`), every value a string: ``classes`` (a JSON list, index = label),
    ``unseen`` (the label of pixels without a ray), ``inputs`` and ``outputs`` (names),
    ``up`` (``input``, ``estimate``, ``none`` or a fixed JSON ``[x, y, z]``), ``up_frame``,
    ``cameras`` (each camera's calibration as ``Camera.key()``, JSON), ``grid``,
    ``interpolation`` and the ``usf_graph`` version that wrote it."""
    from .. import __version__

    mode = bound.up_mode
    up = "estimate" if mode is None else mode if isinstance(mode, str) else json.dumps(mode.tolist())
    return {"usf_graph": __version__, "task": "seg",
            "classes": json.dumps(class_names("seg", bound.model.config["num_classes"])),
            "unseen": str(UNSEEN), "inputs": json.dumps(bound.input_names),
            "outputs": json.dumps(bound.output_names), "up": up,
            "up_frame": "the sphere frame of the camera (of a rig's first camera): x forward, "
                        "y left, z up",
            "cameras": json.dumps({n: io.camera_key for n, io in zip(bound.names, bound.cameras)}),
            "grid": bound.model.input_grid, "interpolation": bound.interpolation}


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
    if any(t.device.type != "cpu" for t in model.parameters()):
        raise ValueError("export traces on the CPU: move the model there first (model.cpu()); "
                         "the written file runs on whatever devices its runtime has")
    t0 = time.perf_counter()
    bound = BoundSegmenter(model, camera, up, interpolation).eval()
    example = bound.example()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.part{path.suffix}")
    with torch.no_grad(), _quiet_exporters():
        with fixed_fields() as fields:  # builds the plain forms' tables, records the masks
            bound(*example)
        with fixed_fields(fields):
            meta = metadata(bound)
            if fmt == "ONNX":
                program = torch.onnx.export(bound, example, dynamo=True, opset_version=OPSET,
                                            input_names=bound.input_names,
                                            output_names=bound.output_names, verbose=False)
                program.model.metadata_props.update(meta)
                program.save(str(tmp))
            else:
                program = torch.export.export(bound, example)
                with _unused_buffers_emptied(bound, program):  # the fast forms' geometry
                    program = torch.export.export(bound, example)
                torch.export.save(program, str(tmp), extra_files={META_FILE: json.dumps(meta)})
    tmp.replace(path)  # atomic: a failed export leaves no half-written file
    info = {"path": str(path), "format": fmt, "bytes": path.stat().st_size,
            "inputs": [f"{n} uint8 [{c.size[0]}, {c.size[1]}, 3] RGB"
                       for n, c in zip(bound.names, bound.cameras)]
            + (["up float32 [3]"] if bound.up_mode == "input" else []),
            "outputs": bound.output_names, "interpolation": bound.interpolation,
            "export_s": time.perf_counter() - t0}
    if check:
        reads = None if bound.up_mode == "none" else up  # an isotropic model reads no up
        info["check"] = check_exported(path, model, camera, reads, bound.interpolation, seed)
    return info


@contextlib.contextmanager
def _quiet_exporters():
    """The exporters' notes that say nothing about this export (torchvision's operators
    skipped, a deprecation inside torch's own pytree code), kept off the user's screen."""
    log = logging.getLogger("torch.onnx._internal.exporter._registration")
    level = log.level
    log.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*LeafSpec", category=FutureWarning)
            yield
    finally:
        log.setLevel(level)


@contextlib.contextmanager
def _unused_buffers_emptied(module: nn.Module, program):
    """Inside, every buffer of ``module`` that ``program`` (its export) never reads, and
    that no read buffer shares its tensor with, is a zero-stride tensor of its shape: a
    ``.pt2`` keeps every buffer of the module, and the fast forms' tables (a jet's
    transposed operator, the float64 geometry) would triple its size. Restored after."""
    users = {n.name: len(n.users) for n in program.graph.find_nodes(op="placeholder")}
    to_buffer = program.graph_signature.inputs_to_buffers

    def owner(fqn):
        mod, _, name = fqn.rpartition(".")
        return module.get_submodule(mod), name

    read = {id(m._buffers[n]) for ph, fqn in to_buffer.items() if users.get(ph, 1)
            for m, n in [owner(fqn)]}
    kept = {}
    for ph, fqn in to_buffer.items():
        m, n = owner(fqn)
        t = m._buffers[n]
        if users.get(ph, 1) == 0 and id(t) not in read:
            kept[(m, n)] = t
            m._buffers[n] = torch.zeros((), dtype=t.dtype, device=t.device).expand(t.shape)
    try:
        yield
    finally:
        for (m, n), t in kept.items():
            m._buffers[n] = t


def load_exported(path, threads: int | None = None):
    """An exported file as a function ``(images, up=None) -> (labels, up [3])`` on numpy
    arrays: ``images`` one ``uint8 [H, W, 3]`` image, or a list of one per camera for a
    rig (``labels`` then a list too); ``up`` given exactly when the program takes it. ONNX
    files run in onnxruntime (on ``threads`` CPU threads; None: its default), ``.pt2``
    files through ``torch.export.load`` (on torch's threads). Load once, call per frame.
    The function's ``metadata`` is the file's :func:`metadata` (class names and more)."""
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
        meta = dict(session.get_modelmeta().custom_metadata_map)
        takes = (len([n for n in names if n != "up"]), "up" in names)

        def call(feeds):
            return session.run(None, dict(zip(names, feeds)))
    else:
        extra = {META_FILE: ""}
        program = torch.export.load(str(path), extra_files=extra).module()
        meta = json.loads(extra[META_FILE]) if extra[META_FILE] else {}
        kinds = [n.meta["val"].dtype for n in program.graph.find_nodes(op="placeholder")
                 if "val" in n.meta]
        takes = (kinds.count(torch.uint8), torch.float32 in kinds)

        def call(feeds):
            with torch.no_grad():
                return [t.numpy() for t in program(*(torch.from_numpy(f) for f in feeds))]

    def run(images, up=None):
        rig = isinstance(images, (list, tuple))
        ims = [np.ascontiguousarray(im, np.uint8) for im in (images if rig else [images])]
        if (len(ims), up is not None) != takes:
            want = f"{takes[0]} image{'s' if takes[0] > 1 else ''}" + (" and up" if takes[1] else "")
            raise ValueError(f"{path} takes {want}; got {len(ims)} image{'s' if len(ims) > 1 else ''}"
                             + (" and up" if up is not None else ""))
        feeds = ims + ([np.asarray(up, np.float32).reshape(3)] if up is not None else [])
        *labels, u = call(feeds)
        return (labels if rig else labels[0]), u
    run.metadata = meta  # what the file says of itself (metadata())
    return run


def _angle(u, v) -> float:
    """The angle (radians) between two directions; 0 where either is missing or NaN (a
    model that reads no up)."""
    if v is None or not np.isfinite(u).all():
        return 0.0
    a, b = np.asarray(u, np.float64), np.asarray(v, np.float64)
    return math.atan2(float(np.linalg.norm(np.cross(a, b))), float(np.dot(a, b)))


def check_exported(path, model: nn.Module, camera, up, interpolation: str, seed: int = 0) -> dict:
    """The exported file against :func:`~usf_graph.train.apply.segment_image` on room
    ``seed`` rendered through ``camera`` (a rig: through each of its cameras, from one
    viewpoint): the share of the cameras' pixels where both give the same label (argmax
    ties and float32 summation order can flip a few), the angle between their ups
    (degrees), and the program's time per frame.

    Raises ``RuntimeError`` when fewer than 99% of the pixels agree, the unseen pixels
    differ, or the program's up estimate is over 0.01 degrees from usf-graph's where that
    estimate is sure (margin at least :data:`TIE_MARGIN`; below, the two may pick either
    of tied candidates, and the labels are compared given the program's up): the file
    would be a silent wrong answer."""
    from ..scenes import make_room
    from ..scenes.render import render

    room = make_room(seed)
    images = [render(room, c, boxes=False).rgb for c in cameras_of(camera)]
    given = None if up is None else [0.0, 0.0, 1.0] if up == "input" else up
    feed = images if is_rig(camera) else images[0]
    ref = segment_image(model, feed, camera, up=given, interpolation=interpolation)
    feed_up = [0.0, 0.0, 1.0] if up == "input" else None
    t0 = time.perf_counter()
    run = load_exported(path)
    load = time.perf_counter() - t0
    labels, u = run(feed, feed_up)
    t0 = time.perf_counter()
    run(feed, feed_up)
    frame = time.perf_counter() - t0
    angle = _angle(u, ref["up"])
    tie = up is None and angle > math.radians(0.01) and (ref.get("margin") or 0.0) < TIE_MARGIN
    if tie:  # the estimate's own scores tie: float32 order picks either; compare the rest
        ref = segment_image(model, feed, camera, up=u, interpolation=interpolation)
    elif up is None and angle > math.radians(0.01):
        raise RuntimeError(f"the exported {path} reads up {math.degrees(angle):.3f} degrees away "
                           "from usf-graph's estimate on a rendered room, where the estimate is "
                           "sure of it. Please report it with the checkpoint and the calibration")
    got = labels if is_rig(camera) else [labels]
    want = ref["labels"] if is_rig(camera) else [ref["labels"]]
    seen = np.concatenate([(w != UNSEEN).ravel() for w in want])
    same = np.concatenate([(g == w).ravel() for g, w in zip(got, want)])
    agree = float(same[seen].mean()) if seen.any() else 1.0
    same_unseen = bool(all(((g == UNSEEN) == (w == UNSEEN)).all() for g, w in zip(got, want)))
    out = {"room": seed, "pixels_seen": int(seen.sum()), "agree": agree,
           "unseen_match": same_unseen, "up_angle_deg": math.degrees(angle), "up_tie": tie,
           "load_s": load, "frame_s": frame}
    if agree < 0.99 or not same_unseen:
        raise RuntimeError(f"the exported {path} disagrees with usf-graph on a rendered room: "
                           f"{100 * agree:.2f}% of the pixels agree, unseen pixels "
                           f"{'match' if same_unseen else 'differ'}. Please report it with "
                           "the checkpoint and the calibration")
    return out


__all__ = ["BoundSegmenter", "CameraIO", "FORMATS", "META_FILE", "check_exported", "export_segmenter", "load_exported", "metadata"]
