"""A trained spherical segmenter or detector bound to one camera, exported as one
self-contained program: ONNX (``.onnx``: onnxruntime, TensorRT, OpenVINO, C++) or
``torch.export`` (``.pt2``: ``torch.export.load``, AOTInductor). What ``usf-graph
export`` runs.

The program takes the camera's image as it comes (``uint8 [H, W, 3]``, RGB) and, where
asked, gravity's up in the camera's sphere frame (``float32 [3]``, e.g. from an IMU), and
returns a segmenter's ``labels uint8 [H, W]`` (:data:`~usf_graph.train.apply.UNSEEN`
where the camera has no ray or its mask ignores the pixel) or a detector's spherical
boxes, classes and scores, and the ``up [3]`` it read (:mod:`usf_graph.train.bound`).
Everything that depends only on the camera and the grid is computed here once and held
as constants: the lifting table, the field of view, every layer's coefficients and the
render table. So the deployed program does per frame what
:func:`~usf_graph.train.apply.segment_image` or
:func:`~usf_graph.train.apply.detect_image` does, and nothing else.

The layers take their plain forms (:mod:`usf_graph.tracing`): gathers into padded rows
and batched products instead of sparse tensors, which neither exporter can take. Export
checks the written program against usf-graph on a procedural room rendered through the
camera (:func:`check_exported`).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..ops import pairwise_box_iou
from ..tracing import fixed_fields
from .apply import UNSEEN, cameras_of, class_names, detect_image, is_rig, segment_image
from .bound import BoundDetector, BoundModel, BoundSegmenter

#: What the exported files are: by their suffix.
FORMATS = {".onnx": "ONNX", ".pt2": "torch.export"}
#: ONNX opset of the files written (the exporter's default in torch 2.13).
OPSET = 18
#: An up estimate's margin under which its best two candidates tie (float32 summation
#: order then picks either): the check compares the rest given the program's up.
TIE_MARGIN = 1e-3
#: The ``.pt2`` archive's extra file that holds :func:`metadata`.
META_FILE = "usf_graph.json"


def _onnx_ready() -> None:
    try:
        import onnx  # noqa: F401
        import onnxscript  # noqa: F401
    except ImportError:
        raise ImportError("ONNX export needs onnx and onnxscript: pip install "
                          "'usf-graph[export]' (or export to .pt2)") from None


def metadata(bound: BoundModel) -> dict[str, str]:
    """What an exported file says of itself (ONNX ``metadata_props``, a ``.pt2``'s
    :data:`META_FILE`), every value a string: ``task`` (``seg`` or ``det``), ``classes``
    (a JSON list, index = label), ``inputs`` and ``outputs`` (names), ``up``
    (``input``, ``estimate``, ``none`` or a fixed JSON ``[x, y, z]``), ``up_frame``,
    ``cameras`` (each camera's calibration as ``Camera.key()``, JSON), ``grid``,
    ``interpolation``, the ``usf_graph`` version that wrote it and the ``provenance`` of the
    export (JSON, :func:`~usf_graph.train.provenance.provenance`); with the estimate inside,
    ``estimate`` (JSON: its ``level_prior`` and whether a ``sign_check`` corrects it); a segmenter's
    ``unseen`` (the label of pixels without a ray), a detector's ``boxes`` (their form)
    and ``decoding`` (JSON: ``k``, ``threshold``, ``nms``, ``drop_hidden``)."""
    from .. import __version__
    from .provenance import provenance

    mode = bound.up_mode
    up = "estimate" if mode is None else mode if isinstance(mode, str) else json.dumps(mode.tolist())
    meta = {"usf_graph": __version__, "task": bound.task,
            "classes": json.dumps(class_names(bound.task, bound.model.config["num_classes"])),
            "inputs": json.dumps(bound.input_names),
            "outputs": json.dumps(bound.output_names), "up": up,
            "up_frame": "the sphere frame of the camera (of a rig's first camera): x forward, "
                        "y left, z up",
            "cameras": json.dumps({n: io.camera_key for n, io in zip(bound.names, bound.cameras)}),
            "grid": bound.model.input_grid, "interpolation": bound.interpolation,
            "provenance": json.dumps(provenance())}
    if mode is None:  # how the estimate inside reads up
        from ..models.upnet import UpNet

        net = next(m for m in bound.model.modules() if isinstance(m, UpNet))
        meta["estimate"] = json.dumps({"level_prior": float(net.level_prior),
                                       "sign_check": net.sign_check is not None})
    if bound.task == "seg":
        meta["unseen"] = str(UNSEEN)
    else:
        meta["boxes"] = ("[lon, lat, fov_x, fov_y, roll] in radians in the sphere frame (lon "
                         "counter-clockwise from x, roll from the local east towards north), "
                         "best first; the detections are the rows with score > 0")
        meta["decoding"] = json.dumps(bound.decoding)
    return meta


def export_format(path) -> str:
    """The format an export to ``path`` writes, by its suffix; refused before any work when
    the suffix names none, or names ONNX and its exporter is not installed."""
    fmt = FORMATS.get(Path(path).suffix.lower())
    if fmt is None:
        raise ValueError(f"{path}: name the file .onnx (ONNX) or .pt2 (torch.export)")
    if fmt == "ONNX":
        _onnx_ready()
    return fmt


def export_model(model: nn.Module, camera, path, up="input", interpolation: str = "auto",
                 check: bool = True, seed: int = 0, **decoding) -> dict:
    """Write ``model`` bound to ``camera`` to ``path``: a spherical segmenter as
    :class:`~usf_graph.train.bound.BoundSegmenter`, a spherical detector as
    :class:`~usf_graph.train.bound.BoundDetector` (``decoding``: its ``k``,
    ``threshold``, ``nms`` and ``drop_hidden``); ONNX for ``.onnx``, ``torch.export`` for
    ``.pt2``. Then, with ``check``, run the written file on a procedural room rendered
    through the camera (room ``seed``) and compare with usf-graph
    (:func:`check_exported`). Returns what it did: the file, its format and size, the
    seconds taken and the check's numbers."""
    path = Path(path)
    fmt = export_format(path)
    if any(t.device.type != "cpu" for t in model.parameters()):
        raise ValueError("export traces on the CPU: move the model there first (model.cpu()); "
                         "the written file runs on whatever devices its runtime has")
    t0 = time.perf_counter()
    if hasattr(model, "decode_image"):
        bound = BoundDetector(model, camera, up, interpolation, **decoding).eval()
    elif decoding:
        raise ValueError(f"{', '.join(decoding)}: options of a detector's decoding, and "
                         f"{type(model).__name__} is not a detector")
    else:
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
                                            output_names=bound.output_names, verbose=False,
                                            optimize=False)
                _fold_constants(program.model)
                program.model.metadata_props.update(meta)
                program.save(str(tmp))
            else:
                program = torch.export.export(bound, example)
                _empty_unread_buffers(program)  # the fast forms' geometry
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
        info["check"] = check_exported(path, model, camera, reads, bound.interpolation, seed,
                                       getattr(bound, "decoding", None))
    return info


def _fold_constants(model) -> None:
    """Constant folding alone, in place of the exporter's default optimization: that one's
    pattern rewrites took 12 of a small detector's 30 s of export (the protocol's detector:
    49.5 s of export against 21.4 s without them) and gained nothing at run time, where
    onnxruntime fuses the graph itself (``benchmarks/export_frame.py``)."""
    import onnxscript.optimizer

    onnxscript.optimizer.fold_constants(model)
    onnxscript.optimizer.remove_unused_nodes(model)


@contextlib.contextmanager
def _quiet_exporters():
    """The exporters' notes that say nothing about this export (torchvision's operators
    skipped, a constant output left out of the initializers' deduplication: the NaN up of
    a model that reads none, a deprecation inside torch's own pytree code, the archive's
    note on tensors that share storage), kept off the user's screen."""
    logs = [logging.getLogger(n) for n in ("torch.onnx._internal.exporter._registration",
                                           "onnx_ir.passes.common.initializer_deduplication")]
    levels = [log.level for log in logs]
    for log in logs:
        log.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*LeafSpec", category=FutureWarning)
            # .pt2 archives of the emptied buffers (_empty_unread_buffers), all on the CPU
            warnings.filterwarnings("ignore", message="No complete tensor found", category=UserWarning)
            yield
    finally:
        for log, level in zip(logs, levels):
            log.setLevel(level)


def _empty_unread_buffers(program) -> None:
    """Every buffer in ``program``'s state that its graph never reads becomes a
    zero-stride tensor of its shape, in place: a ``.pt2`` keeps every buffer of the module,
    and the fast forms' tables (a jet's transposed operator, the float64 geometry) would
    triple its size. The shapes stay, so the graph's signature holds as traced. Names that
    share one tensor are one input the graph reads through one of them, which keeps it."""
    users = {n.name: len(n.users) for n in program.graph.find_nodes(op="placeholder")}
    held = [program.state_dict, program.constants]  # persistent buffers, non-persistent ones
    unread = {fqn for ph, fqn in program.graph_signature.inputs_to_buffers.items()
              if users.get(ph, 1) == 0}
    for d in held:
        for fqn in unread & d.keys():
            t = d[fqn]
            d[fqn] = torch.zeros((), dtype=t.dtype, device=t.device).expand(t.shape)


def load_exported(path, threads: int | None = None):
    """An exported file as a function ``(images, up=None) -> (answer, up [3])`` on numpy
    arrays: ``images`` one ``uint8 [H, W, 3]`` image, or a list of one per camera for a
    rig; ``up`` given exactly when the program takes it. A segmenter's answer is its
    ``labels`` (a list of them for a rig); a detector's ``{"boxes": [D, 5], "classes":
    [D], "scores": [D]}``, its detections best first (the rows scoring above 0). ONNX
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
        sizes = [tuple(i.shape) for i in session.get_inputs() if i.name != "up"]

        def call(feeds):
            return session.run(None, dict(zip(names, feeds)))
    else:
        program, meta = _load_pt2(path)
        kinds = [n.meta["val"].dtype for n in program.graph.find_nodes(op="placeholder")
                 if "val" in n.meta]
        takes = (kinds.count(torch.uint8), torch.float32 in kinds)
        sizes = [tuple(n.meta["val"].shape) for n in program.graph.find_nodes(op="placeholder")
                 if "val" in n.meta and n.meta["val"].dtype == torch.uint8]

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
        for k, (im, size) in enumerate(zip(ims, sizes)):
            if im.shape != size:
                which = f"image {k}" if rig else "the image"
                raise ValueError(f"{which} has shape {tuple(im.shape)}; {path} takes uint8 "
                                 f"{list(size)} (RGB at the size of the camera it was exported "
                                 "for): export it again for this camera's calibration")
        feeds = ims + ([np.asarray(up, np.float32).reshape(3)] if up is not None else [])
        *answer, u = call(feeds)
        if meta.get("task") == "det":
            boxes, classes, scores = answer
            kept = scores > 0
            return {"boxes": boxes[kept].astype(np.float64), "classes": classes[kept],
                    "scores": scores[kept]}, u
        return (answer if rig else answer[0]), u
    run.metadata = meta  # what the file says of itself (metadata())
    return run


# The last .pt2 loaded, by its file's identity: torch.export.load re-traces the program
# (6-7 s for a small detector), and export's check has just loaded the file a caller loads next
_LAST_PT2: dict = {}


def _load_pt2(path: Path):
    """``(program module, metadata)`` of a ``.pt2`` file, loaded once per version of the
    file (same inode, size and modification time) in a row."""
    st = path.stat()
    key = (str(path.resolve()), st.st_ino, st.st_size, st.st_mtime_ns)
    if key not in _LAST_PT2:
        extra = {META_FILE: ""}
        program = torch.export.load(str(path), extra_files=extra).module()
        _LAST_PT2.clear()
        _LAST_PT2[key] = program, json.loads(extra[META_FILE]) if extra[META_FILE] else {}
    return _LAST_PT2[key]


def _angle(u, v) -> float:
    """The angle (radians) between two directions; 0 where either is missing or NaN (a
    model that reads no up)."""
    if v is None or not np.isfinite(u).all():
        return 0.0
    a, b = np.asarray(u, np.float64), np.asarray(v, np.float64)
    return math.atan2(float(np.linalg.norm(np.cross(a, b))), float(np.dot(a, b)))


def check_exported(path, model: nn.Module, camera, up, interpolation: str, seed: int = 0,
                   decoding: dict | None = None) -> dict:
    """The exported file against usf-graph on room ``seed`` rendered through ``camera``
    (a rig: through each of its cameras, from one viewpoint), with the program's own up
    where usf-graph estimates it too: the angle between their ups (degrees), the
    program's time per frame, and for a segmenter the share of the cameras' pixels where
    both give the same label (:func:`~usf_graph.train.apply.segment_image`; argmax ties
    and float32 summation order can flip a few), for a detector (``decoding`` its options)
    the detections both find (:func:`~usf_graph.train.apply.detect_image`;
    :func:`_matched`).

    Raises ``RuntimeError`` when fewer than 99% of the pixels agree or the unseen pixels
    differ, when more than 2% of the detections (and more than one) have no match, or
    when the program's up estimate is over 0.01 degrees from usf-graph's where that
    estimate is sure (margin at least :data:`TIE_MARGIN`; below, the two may pick either
    of tied candidates, and the rest is compared given the program's up): the file would
    be a silent wrong answer."""
    from ..scenes import make_room
    from ..scenes.render import render

    room = make_room(seed)
    images = [render(room, c, boxes=False).rgb for c in cameras_of(camera)]
    feed = images if is_rig(camera) else images[0]
    if decoding is None:
        def reference(u):
            return segment_image(model, feed, camera, up=u, interpolation=interpolation)
    else:
        def reference(u):
            return detect_image(model, feed, camera, up=u, interpolation=interpolation, **decoding)
    ref = reference(None if up is None else [0.0, 0.0, 1.0] if up == "input" else up)
    feed_up = [0.0, 0.0, 1.0] if up == "input" else None
    t0 = time.perf_counter()
    run = load_exported(path)
    load = time.perf_counter() - t0
    got, u = run(feed, feed_up)
    t0 = time.perf_counter()
    run(feed, feed_up)
    frame = time.perf_counter() - t0
    angle = _angle(u, ref["up"])
    tie = up is None and angle > math.radians(0.01) and (ref.get("margin") or 0.0) < TIE_MARGIN
    if tie:  # the estimate's own scores tie: float32 order picks either; compare the rest
        ref = reference(u)
    elif up is None and angle > math.radians(0.01):
        raise RuntimeError(f"the exported {path} reads up {math.degrees(angle):.3f} degrees away "
                           "from usf-graph's estimate on a rendered room, where the estimate is "
                           "sure of it. Please report it with the checkpoint and the calibration")
    out = {"room": seed, "up_angle_deg": math.degrees(angle), "up_tie": tie, "load_s": load,
           "frame_s": frame}
    if decoding is None:
        out.update(_same_labels(got, ref["labels"], is_rig(camera)))
        bad = out["agree"] < 0.99 or not out["unseen_match"]
        said = (f"{100 * out['agree']:.2f}% of the pixels agree, unseen pixels "
                f"{'match' if out['unseen_match'] else 'differ'}")
    else:
        out.update(_matched(got, ref))
        n = max(out["detections"], out["detections_exported"])
        bad = out["unmatched"] > max(1, 0.02 * n)
        said = (f"{out['unmatched']} of {n} detections have no match in the other "
                "(same class, IoU at least 0.95, scores within 1e-3)")
        spread = float(np.ptp(ref["scores"])) if len(ref["scores"]) else 1.0
        if bad and spread < 1e-3:  # float32 rounding then picks among tied peaks
            said += (f"; but usf-graph's own scores all lie within {spread:.1e} of each other, "
                     "so the two pick differently among tied peaks: is the model trained? "
                     "(--no-check writes it unchecked)")
    if bad:
        raise RuntimeError(f"the exported {path} disagrees with usf-graph on a rendered room: "
                           f"{said}. Please report it with the checkpoint and the calibration")
    return out


def _same_labels(got, want, rig: bool) -> dict:
    """How far two segmentations of the same images agree: the share of seen pixels with
    the same label, and whether the unseen pixels are the same."""
    got, want = (got, want) if rig else ([got], [want])
    seen = np.concatenate([(w != UNSEEN).ravel() for w in want])
    same = np.concatenate([(g == w).ravel() for g, w in zip(got, want)])
    return {"pixels_seen": int(seen.sum()), "agree": float(same[seen].mean()) if seen.any() else 1.0,
            "unseen_match": bool(all(((g == UNSEEN) == (w == UNSEEN)).all() for g, w in zip(got, want)))}


def _matched(got: dict, want: dict) -> dict:
    """How far two sets of detections of the same image agree: each of ``want``'s, best
    first, takes the unmatched one of ``got`` of its class that overlaps it most, a match
    where their IoU is at least 0.95 and their scores within 1e-3. Float32 against float64
    decoding: a score at the threshold or an IoU at the NMS threshold can flip, and the
    axes of a nearly square box where the spin fields nearly vanish (at the zenith, about
    which an upright model's fields are symmetric) can turn by a degree. Returns the
    counts, the largest score difference and the smallest IoU of the matches."""
    iou = pairwise_box_iou(torch.as_tensor(want["boxes"]), torch.as_tensor(got["boxes"]),
                           dtype=torch.float64).numpy()
    iou = np.where(want["classes"][:, None] == got["classes"][None, :], iou, -1.0)
    free, matched, worst, least = np.ones(len(got["boxes"]), bool), 0, 0.0, 1.0
    for i in range(len(want["boxes"])):
        j = int(np.argmax(np.where(free, iou[i], -1.0))) if free.any() else -1
        diff = abs(float(want["scores"][i]) - float(got["scores"][j])) if j >= 0 else 1.0
        if j >= 0 and free[j] and iou[i, j] >= 0.95 and diff <= 1e-3:
            free[j], matched = False, matched + 1
            worst, least = max(worst, diff), min(least, float(iou[i, j]))
    unmatched = len(want["boxes"]) - matched + int(free.sum())
    return {"detections": len(want["boxes"]), "detections_exported": len(got["boxes"]),
            "matched": matched, "unmatched": unmatched, "score_diff": worst, "iou_min": least}


__all__ = ["FORMATS", "META_FILE", "check_exported", "export_format", "export_model", "load_exported", "metadata"]
