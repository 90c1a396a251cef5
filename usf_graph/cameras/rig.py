"""A rig's cameras: mounted by their poses, and stitched at a distance."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from .base import DEFAULT_ROTATION, Camera


def mount(cam: Camera, pose) -> Camera:
    """``cam`` placed in a rig by ``pose [4, 4]`` (the rig's first optical frame <- the
    camera's optical frame): turned to the sphere frame (x forward, y left, z up), its
    optical centre at ``position``."""
    return cam.with_rotation(DEFAULT_ROTATION @ pose[:3, :3]).with_position(
        DEFAULT_ROTATION @ pose[:3, 3])


def rig_centre(rig: Mapping[str, Camera], centre="mean") -> tuple[np.ndarray, float]:
    """``(centre [3], reach)``: the centre a rig is stitched about (``"mean"``: the cameras'
    mean position, or 3 numbers in the rig's sphere frame) and the farthest camera's
    distance from it, which a stitching distance must exceed."""
    missing = [n for n, c in rig.items() if c.position is None]
    if missing:
        raise ValueError(f"camera(s) {missing} have no position, so the distance cannot place "
                         "them; read the rig with cameras.load_rig, or set positions with "
                         "camera.with_position")
    pos = np.stack([c.position for c in rig.values()])
    if isinstance(centre, str):
        if centre != "mean":
            raise ValueError(f"centre must be 'mean' or 3 numbers, got {centre!r}")
        c0 = pos.mean(0)
    else:
        c0 = np.asarray(centre, np.float64)
        if c0.shape != (3,) or not np.isfinite(c0).all():
            raise ValueError(f"centre must be 3 finite numbers, got {centre!r}")
    return c0, float(np.linalg.norm(pos - c0, axis=1).max())


def stitch_at(rig: Mapping[str, Camera], distance: float | None, centre="mean") -> dict[str, Camera]:
    r"""A rig's cameras that see the scene as a sphere of radius ``distance`` about
    ``centre``: each camera then looks at the sphere's direction :math:`p` along
    :math:`r p - t_c` from its optical centre :math:`t_c`, so that a scene point at that
    distance lands on one direction in every camera (the stitching distance of 360-degree
    cameras). Nearer or farther points still show parallax, less the farther they are.

    Args:
        rig: ``{name: camera}`` with positions (:func:`usf_graph.cameras.load_rig`).
        distance: the radius, in the unit of the positions (metres for Kalibr, Basalt and
            ORB-SLAM3; COLMAP's model unit); beyond every camera. ``None``: at infinity,
            the cameras share one centre (their positions are left as they are).
        centre: the sphere's centre in the rig's sphere frame: ``"mean"`` (the cameras'
            mean position) or 3 numbers. Positions are made relative to it.
    """
    if distance is None:
        return {n: c.with_distance(None) for n, c in rig.items()}
    c0, far = rig_centre(rig, centre)
    if not far < distance:
        raise ValueError(f"the distance {distance:g} does not reach past the rig: a camera is "
                         f"{far:.4g} from the centre; give a distance beyond {far:.4g}, in the "
                         "unit of the cameras' positions")
    return {n: c.with_position(c.position - c0).with_distance(distance) for n, c in rig.items()}
