"""Random fields of view: parts of the sphere as narrower lenses show them, for training a
spherical model that must also work through those lenses (a pinhole sees a sixth of it)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ..cameras import Camera, Pinhole
from ..geometry import random_rotation, rotation_from_axis_angle
from .engine import fit

#: Field-of-view range (degrees, each axis) of :func:`random_frustum`'s pinholes.
FRUSTUM_DEGREES = (60.0, 120.0)
#: Angular radius range (degrees) of :func:`random_cap`'s caps, fisheye-like fields of view.
CAP_DEGREES = (45.0, 100.0)
#: The second training phase through random fields of view that both protocols use (det
#: and seg, README): the share of batches cut, and its learning rate.
FOV_SHARE, FOV_LR = 0.5, 5e-4


def _uniform(lo: float, hi: float, generator: torch.Generator | None) -> float:
    return lo + (hi - lo) * float(torch.rand((), generator=generator))


def random_cap(pos: torch.Tensor, min_deg: float = CAP_DEGREES[0], max_deg: float = CAP_DEGREES[1],
               generator: torch.Generator | None = None) -> torch.Tensor:
    """A field of view ``[N]`` (bool) over points ``pos [N, 3]``: a cap of uniform random
    angular radius in ``[min_deg, max_deg]`` about a uniform random direction."""
    c = torch.nn.functional.normalize(torch.randn(3, generator=generator, dtype=torch.float64), dim=0)
    return pos.double() @ c.to(pos.device) > math.cos(math.radians(_uniform(min_deg, max_deg, generator)))


def random_pinhole(min_deg: float = FRUSTUM_DEGREES[0], max_deg: float = FRUSTUM_DEGREES[1],
                   generator: torch.Generator | None = None, size: int = 64) -> Pinhole:
    """A ``size x size`` :class:`~usf_graph.cameras.Pinhole` whose horizontal and vertical
    fields of view are drawn uniformly from ``[min_deg, max_deg]``, mounted with a
    Haar-random rotation."""
    f = [size / 2 / math.tan(math.radians(_uniform(min_deg, max_deg, generator)) / 2)
         for _ in range(2)]
    R = random_rotation(generator=generator).numpy()
    c = (size - 1) / 2  # the image spans c -+ size / 2: the drawn fields of view exactly
    return Pinhole(f[0], f[1], c, c, size, size, rotation=R)


def random_frustum(pos: torch.Tensor, min_deg: float = FRUSTUM_DEGREES[0],
                   max_deg: float = FRUSTUM_DEGREES[1],
                   generator: torch.Generator | None = None) -> torch.Tensor:
    """What a :func:`random_pinhole` sees of points ``pos [N, 3]``: ``[N]`` (bool)."""
    cam = random_pinhole(min_deg, max_deg, generator)
    return torch.as_tensor(np.asarray(cam.sees(pos.double().numpy())[1], bool))


def random_field_of_view(pos: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
    """A :func:`random_frustum` or a :func:`random_cap` (default ranges), with equal odds."""
    pick = random_frustum if float(torch.rand((), generator=generator)) < 0.5 else random_cap
    return pick(pos, generator=generator)


def _check_turn(turn: str) -> str:
    if turn not in ("yaw", "so3"):
        raise ValueError(f"turn must be 'yaw' or 'so3', got {turn!r}")
    return turn


def camera_field(camera: Camera, pos: torch.Tensor, turn: str = "yaw",
                 generator: torch.Generator | None = None) -> torch.Tensor:
    """What ``camera`` sees of points ``pos [N, 3]`` once turned at random: ``[N]`` (bool).
    ``turn="yaw"``: its own mounting turned about +z (the gravity of upright views) by a
    uniform angle, so a level camera stays level, as a robot's does when it turns;
    ``"so3"``: mounted with a Haar-random rotation instead."""
    if _check_turn(turn) == "yaw":
        a = 2 * math.pi * float(torch.rand((), generator=generator, dtype=torch.float64))
        R = rotation_from_axis_angle(np.array([0.0, 0.0, 1.0]), a) @ camera.rotation
    else:
        R = random_rotation(generator=generator).numpy()
    return torch.as_tensor(np.asarray(camera.with_rotation(R).sees(pos.double().numpy())[1], bool))


class FieldDraws:
    """The state of a ``collate_fn`` that cuts batches through :class:`RandomFields`
    (``self.fields``): :func:`~usf_graph.train.engine.fit` saves it with ``last.pt`` and
    restores it on resume, so that a resumed run draws the fields an uninterrupted one
    would."""

    fields: RandomFields

    def state_dict(self) -> dict:
        return {"generator": self.fields.generator.get_state()}

    def load_state_dict(self, state: dict) -> None:
        self.fields.generator.set_state(state["generator"])


def check_share(share: float) -> None:
    """Refuse a share of batches (``fov_share``) outside [0, 1], the protocols before any
    rendering and :class:`RandomFields` when built."""
    if not 0 <= share <= 1:
        raise ValueError(f"the share of batches through random fields of view must be in "
                         f"[0, 1], got {share}")


class RandomFields:
    """Fields of view to train a share of the batches through: ``fields(mask)`` is ``None``
    (leave this batch whole) with probability ``1 - share``, else one
    :func:`random_field_of_view` over the grid points ``pos [N, 3]`` (with ``camera``:
    what that camera sees turned at random, :func:`camera_field` with ``turn``), within
    ``mask [N]`` (a camera's own field of view; ``None``: the whole sphere), or ``None``
    where the two do not meet. ``seed``: of the draws, which follow one another across
    calls."""

    def __init__(self, pos: torch.Tensor, share: float, seed: int = 0,
                 camera: Camera | None = None, turn: str = "yaw"):
        check_share(share)
        if pos.dim() != 2 or pos.shape[1] != 3:
            raise ValueError(f"pos must be the grid's points [N, 3], got {tuple(pos.shape)}")
        self.pos, self.share = pos.double(), float(share)
        self.camera, self.turn = camera, _check_turn(turn)
        self.generator = torch.Generator().manual_seed(int(seed))

    def __call__(self, mask: torch.Tensor | None = None) -> torch.Tensor | None:
        if float(torch.rand((), generator=self.generator)) >= self.share:
            return None
        seen = random_field_of_view(self.pos, self.generator) if self.camera is None else \
            camera_field(self.camera, self.pos, self.turn, self.generator)
        seen = seen if mask is None else seen & mask.bool()
        return seen if seen.any() else None


def second_phase(net, train, epochs: int, log_dir, name: str, cut=None, collate_fn=None,
                 **fit_kw) -> None:
    """Both protocols' second phase: ``net`` trains ``epochs`` more on ``train`` at
    ``FOV_LR``, logging under ``log_dir / "second_phase"`` (``fit_kw``: the rest of
    :func:`~usf_graph.train.engine.fit`'s arguments). ``cut``: a ``collate_fn`` that sees
    a share of the batches through random fields of view (e.g. one over
    :class:`RandomFields`); the normalizations are then frozen
    (:func:`~usf_graph.train.engine.freeze_norms`), as a cut batch's statistics are those
    of one part of one view. Without it (a planar model, with no field of view to cut) the
    model trains on the whole views through ``collate_fn``, so that every model trains as
    long. ``epochs`` 0: no second phase."""
    if not epochs:
        return
    fit(net, train, None, epochs=epochs, lr=FOV_LR, log_dir=Path(log_dir) / "second_phase",
        name=f"{name}, second phase", frozen_norms=cut is not None,
        collate_fn=collate_fn if cut is None else cut, **fit_kw)
