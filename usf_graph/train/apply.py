"""A trained spherical model on one image from any calibrated camera (or one frame of a
rig): the image is lifted onto the model's grid through its camera, and the answer comes
back in that camera's terms (labels in its pixels, boxes in its sphere frame). What
``usf-graph predict`` runs.

The protocols train on RGB in [0, 1] lifted bilinearly from images about as fine as the
grid; :func:`lift_for` lifts any image the same way, and averages over each grid cell
(``area``) where the image is much finer than the grid, so that a 4K fisheye does not
alias into what the model never saw.
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Mapping
from contextlib import contextmanager

import numpy as np
import torch

from ..frontend import SphericalFrontend
from ..frontend.image import unit_range
from ..frontend.interpolation import choose_interpolation, valid_pixels
from ..grids import from_spec
from .devices import model_device

#: Unseen pixels of a label image (the datasets' ignore index).
UNSEEN = 255

_GEOMETRY: dict = {}  # per-camera results, so that the frames of one camera compute them once


def _per_camera(what: str, camera, build, extra=None):
    """``build()``, once per camera geometry (:meth:`~usf_graph.cameras.Camera.key`; a
    list of cameras for a rig)."""
    cams = camera if isinstance(camera, list) else [camera]
    key = (what, json.dumps([c.key() for c in cams], sort_keys=True), extra)
    if key not in _GEOMETRY:
        if len(_GEOMETRY) >= 16:  # a few cameras' frontends at most
            _GEOMETRY.clear()
        _GEOMETRY[key] = build()
    return _GEOMETRY[key]


def class_names(task: str, num_classes: int) -> list[str]:
    """The class names of a protocol model: the 13 Stanford 2D-3D-S classes or WoodScape's
    10 (seg), the rooms' 12 or PANDORA's 47 (det), told apart by their number, else
    ``class k``."""
    from ..datasets.woodscape import CLASSES as WOODSCAPE_CLASSES
    from ..scenes import DETECTION_CLASSES, PANDORA_CLASSES, SEMANTIC_CLASSES

    known = [SEMANTIC_CLASSES, WOODSCAPE_CLASSES] if task == "seg" else [DETECTION_CLASSES, PANDORA_CLASSES]
    for names in known:
        if len(names) == num_classes:
            return list(names)
    return [f"class {k}" for k in range(num_classes)]


def input_grid(model):
    """The grid a spherical protocol model reads (``model.input_grid``), or a clear error
    for a planar one, which reads panoramas of one size and no other camera."""
    spec = getattr(model, "input_grid", None)
    if spec is None:
        raise ValueError(f"{type(model).__name__} is planar: it reads equirectangular images of "
                         "its training size only; predict with a spherical checkpoint")
    return from_spec(spec)


def _auto(camera, grid) -> str:
    return _per_camera("interpolation", camera, lambda: choose_interpolation(camera, grid), grid.spec)


def auto_interpolation(cameras: list, grid) -> str:
    """``interpolation="auto"`` for one camera or a rig's (:func:`choose_interpolation`):
    ``area`` if any of them needs it."""
    return "area" if "area" in {_auto(c, grid) for c in cameras} else "bilinear"


def cameras_of(camera) -> list:
    """The cameras of ``camera``: itself alone, or a rig's (a list, or a mapping's values)
    in their order."""
    if isinstance(camera, Mapping):
        return list(camera.values())
    return list(camera) if is_rig(camera) else [camera]


def rgb_channels(image, colour_model: bool = True) -> np.ndarray:
    """``image``'s three colour channels ``[H, W, 3]``, in its dtype: a fourth (alpha)
    channel is dropped, and a grayscale image (``[H, W]`` or ``[H, W, 1]``: a mono camera's)
    is read as R = G = B, with a warning where it goes to a ``colour_model`` (one not
    trained with ``--gray``)."""
    a = np.asarray(image)
    if a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 1):
        if colour_model:
            warnings.warn("a grayscale image is read as R = G = B by a model trained on colour "
                          "images, which costs it much (README, Your own images: Mono cameras); "
                          "train one for mono cameras with --gray", stacklevel=3)
        return np.repeat(a.reshape(*a.shape[:2], 1), 3, axis=2)
    if a.ndim != 3 or a.shape[2] not in (3, 4):
        raise ValueError(f"the models read RGB images [H, W, 3] (or grayscale [H, W]), got shape "
                         f"{a.shape}; convert other channel counts to RGB first")
    return a[..., :3]


def rgb01(image, colour_model: bool = True) -> np.ndarray:
    """An RGB image as float32 in [0, 1], ``[H, W, 3]`` (:func:`rgb_channels`): uint8 /
    255, uint16 / 65535, float as it is (checked to lie in [0, 1])."""
    return unit_range(rgb_channels(image, colour_model))


def lift_for(model, image, camera, interpolation: str = "auto", image_mask=None):
    """``(frontend, x [1, N, 3], mask [N] or None)``: ``image`` (see :func:`rgb01`) lifted
    through ``camera`` onto ``model``'s grid. ``interpolation``: a
    :class:`~usf_graph.frontend.SphericalFrontend` method, or ``auto``
    (:func:`choose_interpolation`; for a rig, ``area`` if any of its cameras needs it).
    ``image_mask [H, W]``: False on pixels to ignore. ``x`` and ``mask`` are on the device
    the model is on.

    A rig: ``camera`` a list or ``{name: camera}`` of cameras mounted by their
    ``rotation`` (:func:`usf_graph.cameras.load_rig`) and ``image`` one image per camera
    (a list in that order, or ``{name: image}``), lifted onto one sphere
    (:class:`~usf_graph.frontend.RigFrontend`, the frontend returned); their masks go
    with the cameras (:func:`usf_graph.cameras.with_fov_and_mask`)."""
    grid, colour = input_grid(model), not getattr(model, "gray", False)
    if not is_rig(camera):
        rgb = rgb01(image, colour)  # before any table is built: a wrong image costs nothing
        if interpolation == "auto":
            interpolation = auto_interpolation([camera], grid)
        if image_mask is not None:
            camera = camera.with_image_mask(image_mask, combine=True)
        # one frontend per camera: its remap maps are built on its first lift, not per frame
        fe = _per_camera("frontend", camera, lambda: SphericalFrontend(camera, grid, interpolation),
                         (grid.spec, interpolation))
        return _on_model(model, fe, fe.lift(rgb)[None])
    from ..frontend import RigFrontend

    if image_mask is not None:
        raise ValueError("a rig's image masks go with its cameras: cameras.with_fov_and_mask")
    cams = cameras_of(camera)
    rgb = {k: rgb01(v, colour) for k, v in image.items()} if isinstance(image, Mapping) else \
        [rgb01(v, colour) for v in image]
    if interpolation == "auto":
        interpolation = auto_interpolation(cams, grid)
    fe = _per_camera("rig", cams, lambda: RigFrontend(camera, grid, interpolation=interpolation),
                     (grid.spec, interpolation, tuple(camera) if isinstance(camera, Mapping) else None))
    return _on_model(model, fe, fe.lift(rgb)[None])


def _on_model(model, fe, x):
    """``(fe, x, mask)`` with the lifted ``x`` and the field of view on ``model``'s device
    (the mask None where the frontend sees everything)."""
    dev = model_device(model)
    return fe, x.to(dev), None if fe.mask.all() else fe.mask.to(dev)


def is_rig(camera) -> bool:
    """Whether ``camera`` is several cameras (a list or a mapping): a rig."""
    return isinstance(camera, (list, tuple, Mapping))


def _frontends(fe) -> list:
    """The single-camera frontends that give the answer back: one, or a rig's."""
    return list(getattr(fe, "frontends", [fe]))


@contextmanager
def _evaluating(model):
    """The model in evaluation mode (its up estimate polishes, its norms use running
    statistics), its own mode restored after."""
    was = model.training
    model.eval()
    try:
        yield
    finally:
        model.train(was)


def _up(up, x: torch.Tensor) -> torch.Tensor | None:
    """A given ``up`` as ``[1, 3]`` unit vector in ``x``'s dtype and on its device."""
    if up is None:
        return None
    u = torch.as_tensor(np.asarray(up, np.float64).reshape(-1))
    if u.shape != (3,) or not torch.isfinite(u).all() or u.norm() < 1e-9:
        raise ValueError(f"up must be 3 finite numbers, not all 0 (the gravity's up in the "
                         f"camera's sphere frame: x forward, y left, z up), got {up}")
    return (u / u.norm()).to(x.device, x.dtype)[None]


def _lines_up(model, image, fe, x: torch.Tensor, mask) -> tuple[torch.Tensor | None, dict]:
    """``up="lines"``: the model's up estimate picks among the Manhattan axes of the
    image's straight lines (:func:`~usf_graph.train.gravity.estimate_up` with ``axes``) ->
    ``([1, 3] or None, its info)``; ``None`` (the estimate as it is) when the image has too
    few lines. Any camera (a :class:`~usf_graph.frontend.lines.LineFinder`, built once per
    camera, straightens a fisheye's or a panorama's lines through pinholes), and a rig (its
    cameras' lines together)."""
    from ..frontend.lines import LineFinder, manhattan_axes
    from ..frontend.rig import ordered_images
    from ..models.gravity import UNSURE_MARGIN
    from .gravity import estimate_up, require_up_estimate

    require_up_estimate(model, "up='lines'")
    if isinstance(fe, SphericalFrontend):
        cams, images = fe.camera, rgb01(image, colour_model=False)  # warned at lift
    else:  # a rig: its images in its cameras' order
        cams = [f.camera for f in fe.frontends]
        images = [rgb01(im, colour_model=False) for im in ordered_images(fe.names, image)]
    axes = manhattan_axes(*_per_camera("lines", cams, lambda: LineFinder(cams))(images))
    if axes is None:
        return None, {"lines": "too few straight lines: the estimate"}
    up, margin = estimate_up(model.gravity, x, mask, axes=torch.as_tensor(axes)[None])
    m = float(margin[0])
    return up.to(x.device, x.dtype), {"source": "lines", "margin": m, "unsure": m < UNSURE_MARGIN}


def _read_up(model, up, image, fe, x, mask) -> tuple[torch.Tensor | None, dict]:
    """The up handed to the model (``[1, 3]`` or ``None``: its own estimate) and how it was
    found, from :func:`segment_image`'s ``up``."""
    if isinstance(up, str):
        if up != "lines":
            raise ValueError(f"up must be 3 numbers, None (the model's estimate) or 'lines', got {up!r}")
        return _lines_up(model, image, fe, x, mask)
    given = _up(up, x)
    return given, {} if given is None else {"source": "given"}


def _up_info(given, grav, how: dict | None = None) -> dict:
    """The up the model read: given (``how``: by whom), or estimated with its margin (None
    without one)."""
    if given is not None:
        return {"up": given[0].tolist(), "source": "given", **(how or {})}
    if grav is None:
        return {"up": None, "source": "none"}
    from ..models.gravity import UNSURE_MARGIN

    margin = float(grav["margin"][0]) if "margin" in grav else None
    return {"up": grav["up"][0].tolist(), "source": "estimated", "margin": margin,
            "unsure": margin is not None and margin < UNSURE_MARGIN, **(how or {})}


@torch.no_grad()
def segment_image(model, image, camera, up=None, interpolation: str = "auto",
                  image_mask=None, render: str = "nearest") -> dict:
    """A trained spherical segmenter on one image of ``camera``.

    ``up``: gravity's up in the camera's sphere frame (an IMU), else the model's estimate;
    ``"lines"``: the estimate's pick among the Manhattan axes of the
    image's straight lines (:mod:`usf_graph.frontend.lines`; the estimate where it has too
    few). A rig (:func:`lift_for`) is segmented as one sphere. Returns ``{"labels": [H, W]
    uint8 in the camera's pixels (:data:`UNSEEN` where it has no ray or the mask ignores
    it; for a rig a list, one per camera), "points": [N] uint8 per grid point (UNSEEN
    outside the field of view), "probs": [N, C] float32, "up": ..., "interpolation":
    ...}``. ``render``: how the labels reach the pixels
    (:meth:`~usf_graph.frontend.SphericalFrontend.to_labels`: ``nearest`` or ``soft``)."""
    fe, x, mask = lift_for(model, image, camera, interpolation, image_mask)
    with _evaluating(model):
        given, how = _read_up(model, up, image, fe, x, mask)
        if given is None:
            logits, grav = model(x, mask, return_gravity=True)
        else:
            logits, grav = model(x, mask, up=given), None
    probs = logits[0].softmax(-1).cpu()
    points = probs.argmax(-1).to(torch.uint8)
    labels = []
    for f in _frontends(fe):
        lab = f.to_labels(probs, render).to(torch.uint8).numpy()
        lab[~_seen_pixels(f)] = UNSEEN
        labels.append(lab)
    points[~fe.mask] = UNSEEN
    return {"labels": labels if is_rig(camera) else labels[0], "points": points.numpy(),
            "probs": probs.float().numpy(), "interpolation": _frontends(fe)[0].interpolation,
            **_up_info(given, grav, how)}


@torch.no_grad()
def detect_image(model, image, camera, up=None, interpolation: str = "auto", image_mask=None,
                 threshold: float = 0.05, k: int = 100, nms: float | None = 0.5,
                 drop_hidden: bool = True) -> dict:
    """A trained spherical detector on one image of ``camera`` (or a rig's images, as one
    sphere: :func:`lift_for`): ``{"boxes": [D, 5] (radians, the camera's or the rig's
    sphere frame; :mod:`usf_graph.ops.boxes`), "classes": [D],
    "scores": [D], "up": ..., "interpolation": ...}``, best first. ``up`` as
    :func:`segment_image`'s; ``threshold``, ``k``, ``nms``, ``drop_hidden`` as
    :meth:`~usf_graph.models.SphericalDetector.decode_image`'s."""
    fe, x, mask = lift_for(model, image, camera, interpolation, image_mask)
    with _evaluating(model):
        given, how = _read_up(model, up, image, fe, x, mask)
        out = model(x, mask) if given is None else model(x, mask, up=given)
    found = model.decode(out, k=k, threshold=threshold, nms=nms, drop_hidden=drop_hidden)[0]
    return {**found, "interpolation": _frontends(fe)[0].interpolation,
            **_up_info(given, out.get("gravity"), how)}


def _seen_pixels(fe: SphericalFrontend) -> np.ndarray:
    """``[H, W]`` bool: pixels with a ray, less those its camera's image mask ignores."""
    cam = fe.camera
    return _per_camera("rays", cam, lambda: valid_pixels(cam))
