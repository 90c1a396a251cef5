"""Rendering a room through any camera: RGB, labels, instances, depth and spherical boxes.

Pixel rays come from the camera's lens normal map, turned into the world by the view's
``rotation`` (world <- view sphere frame); first hits come from Embree through trimesh.
Labels, instances and depth are those of each pixel's centre ray. RGB is Lambertian shading
of mip-mapped textures, supersampled (2 x 2 rays) on pixels at an object's edge.
"""

from __future__ import annotations

import functools
import json
import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from ..cameras import Camera
from ..cameras.base import check_rotation
from ..geometry import normalize
from ..ops.boxes import box_axes, fit_box, rotate_boxes
from .classes import IGNORE
from .room import Scene
from .textures import sample

#: Angular spacing (degrees) of the spherical ray cast that gives the boxes.
BOX_SPACING_DEG = 0.4
#: An object gets a box when its visible part covers at least this solid angle (sr) ...
MIN_SOLID_ANGLE = 5e-4
#: ... and a view keeps it when the camera sees at least this fraction of that part.
MIN_VISIBLE_FRACTION = 0.5


@dataclass
class View:
    """One rendering. Images are ``[H, W]`` in the camera's pixels; boxes are in the view's
    sphere frame (the frame the camera's lens normal map is in), ``[lon, lat, fov_x, fov_y,
    roll]`` in radians (see :mod:`usf_graph.ops.boxes`)."""

    rgb: np.ndarray        # [H, W, 3] uint8
    label: np.ndarray      # [H, W] uint8, Stanford class index, IGNORE where no ray
    instance: np.ndarray   # [H, W] int32, -1 where no ray
    depth: np.ndarray      # [H, W] float32, metres along the ray, 0 where no ray
    valid: np.ndarray      # [H, W] bool
    boxes: np.ndarray      # [K, 5] float64
    box_class: np.ndarray  # [K] int64, index into DETECTION_CLASSES
    box_instance: np.ndarray  # [K] int64
    position: np.ndarray   # [3] world, the camera's optical centre (depth is from it)
    rotation: np.ndarray   # [3, 3] world <- view


_RAYS: OrderedDict = OrderedDict()


def _camera_rays(cam: Camera):
    """Lens normal map, validity and each pixel's angular size (rad), cached per camera."""
    key = json.dumps(cam.key(), sort_keys=True)
    if key not in _RAYS:
        lnm, valid = cam.lens_normal_map()
        d = np.nan_to_num(lnm)
        du = np.linalg.norm(np.diff(d, axis=1, append=d[:, -1:]), axis=-1)
        dv = np.linalg.norm(np.diff(d, axis=0, append=d[-1:]), axis=-1)
        size = np.maximum(du, dv)
        good = valid & (size > 0) & (size < 0.5)
        size = np.where(good, size, np.median(size[good]) if good.any() else 0.01)
        _RAYS[key] = (lnm, valid, size)
        while len(_RAYS) > 8:
            _RAYS.popitem(last=False)
    _RAYS.move_to_end(key)
    return _RAYS[key]


def shade(scene: Scene, origin, dirs, inst, t, face, pix_size) -> np.ndarray:
    """Colours ``[M, 3]`` in [0, 1] of first hits: texture times tint, Lambertian light."""
    p = origin + dirs * t[:, None]
    n = scene.mesh.face_normals[face]
    n = np.where(((n * dirs).sum(-1) > 0)[:, None], -n, n)  # face the viewer
    # Vertical faces: u to the viewer's right, v down, so pictures read the right way round.
    right = normalize(np.stack([-n[:, 1], n[:, 0], np.zeros(len(n))], -1), 1e-12)
    flat = np.abs(n[:, 2]) > 0.7
    uv = np.where(flat[:, None], p[:, :2], np.stack([(p * right).sum(-1), -p[:, 2]], -1))
    ap = scene.appearance
    tile = ap["tile"][inst]
    cos_in = np.maximum(np.abs((n * dirs).sum(-1)), 0.2)
    tex = sample(ap["texture"][inst], uv / tile[:, None] + ap["offset"][inst], t * pix_size / cos_in / tile)
    mix = ap["mix"][inst][:, None]
    albedo = np.clip(ap["tint"][inst] * (1 - mix + mix * tex), 0, 1)
    to_light = scene.light - p
    dist = np.linalg.norm(to_light, axis=-1)
    lam = np.maximum((n * to_light).sum(-1) / np.maximum(dist, 1e-9), 0)
    light = scene.ambient + (1 - scene.ambient) * lam * 9.0 / (9.0 + dist ** 2) * 1.3
    return np.clip(albedo * light[:, None], 0, 1)


def edge_pixels(inst: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Valid pixels whose instance differs from a 4-neighbour's."""
    e = np.zeros_like(valid)
    dh = inst[:, 1:] != inst[:, :-1]
    dv = inst[1:] != inst[:-1]
    e[:, 1:] |= dh
    e[:, :-1] |= dh
    e[1:] |= dv
    e[:-1] |= dv
    return e & valid


def world_boxes(scene: Scene, position, spacing_deg: float = BOX_SPACING_DEG):
    """Boxes of the objects seen from ``position``, in the world frame with roll 0 (vertical
    axis up), from a dense spherical ray cast that does not depend on any lens.

    The cast has ``spacing_deg`` between rays; each box is then refined by strips of rays
    five times finer just outside its sides (:func:`_refine`), so it is tight to about
    ``spacing_deg / 5``. Returns ``(boxes [K, 5], classes [K], instances [K], rays)``, where
    ``rays[k]`` holds the cast's directions that hit instance k (for field-of-view tests).
    Cached on the scene.
    """
    position = scene.check_viewpoint(position)
    key = (tuple(np.round(position, 12)), float(spacing_deg))
    if key in scene._boxes:
        return scene._boxes[key]
    n = int(round(4 * math.pi / math.radians(spacing_deg) ** 2))
    dirs = _fib(n)
    inst, _, _ = scene.cast(position, dirs)
    order = np.argsort(inst, kind="stable")
    ids, starts = np.unique(inst[order], return_index=True)
    hits = {}
    for k, g in zip(ids, np.split(order, starts[1:])):
        obj = scene.instances[k] if k >= 0 else None
        if obj is not None and obj.detect is not None and len(g) * 4 * math.pi / n >= MIN_SOLID_ANGLE:
            hits[int(k)] = dirs[g]
    boxes = {k: fit_box(d) for k, d in hits.items()}
    for _ in range(2):
        boxes = _refine(scene, position, boxes, hits, math.radians(spacing_deg))
    owners = [k for k in hits if boxes[k] is not None]
    out = (np.array([boxes[k] for k in owners], np.float64).reshape(-1, 5),
           np.array([scene.instances[k].detect for k in owners], np.int64),
           np.array(owners, np.int64), [hits[k] for k in owners])
    scene._boxes[key] = out
    return out


def _refine(scene: Scene, position, boxes: dict, hits: dict, s: float) -> dict:
    """Cast strips of rays ``s / 5`` apart just outside each box's sides (one cast for all
    boxes) and refit each box with what its object there."""
    rays, owner = [], []
    for k, b in boxes.items():
        if b is None:
            continue
        c, e, n = box_axes(b)
        for half, other, ax, bx in ((b[2] / 2, b[3] / 2, e, n), (b[3] / 2, b[2] / 2, n, e)):
            across = np.tan(np.linspace(half - s / 5, min(half + s, 1.55), 6))
            along = np.tan(np.arange(-min(other + s, 1.55), min(other + s, 1.55), s / 5))
            for sign in (-1, 1):
                a, o = np.meshgrid(sign * across, along, indexing="ij")
                r = (c + a[..., None] * ax + o[..., None] * bx).reshape(-1, 3)
                rays.append(r)
                owner.append(np.full(len(r), k))
    if not rays:
        return boxes
    rays, owner = normalize(np.concatenate(rays)), np.concatenate(owner)
    got = scene.cast(position, rays)[0]
    out = dict(boxes)
    for k in np.unique(owner[got == owner]):
        hits[k] = np.concatenate([hits[k], rays[(owner == k) & (got == k)]])
        out[k] = fit_box(hits[k], centre=box_axes(boxes[k])[0])
    return out


@functools.lru_cache(maxsize=1)
def _fib(n: int) -> np.ndarray:
    from ..grids import fibonacci

    return fibonacci(n).pos.numpy()


def render(scene: Scene, camera: Camera, position=None, rotation=None, view: int = 0,
           boxes: bool = True) -> View:
    """Render ``scene`` through ``camera`` from ``position`` with ``rotation``.

    Args:
        scene: a room from :func:`make_room`.
        camera: any :mod:`usf_graph.cameras` model; its own ``rotation`` mounts it in the
            view's sphere frame as usual, and its ``position`` (a rig's camera, metres)
            places its optical centre off the view's centre; a stitching ``distance`` is
            not used, the rays are cast into the room.
        position: the view's centre in metres (world frame); ``scene.viewpoint(view)`` when
            None.
        rotation: ``[3, 3]`` world <- view, any SO(3) rotation; the gravity-aligned random
            yaw of ``scene.viewpoint(view)`` when None.
        view: index of the seeded viewpoint used for whatever is None.
        boxes: compute the view's spherical boxes (see :func:`world_boxes`).
    """
    if position is None or rotation is None:
        p0, r0 = scene.viewpoint(view)
        position = p0 if position is None else position
        rotation = r0 if rotation is None else rotation
    centre = scene.check_viewpoint(position)
    rotation = check_rotation(rotation)
    camera = camera.with_distance(None)  # its rays, not a stitching sphere's directions
    position = centre if camera.position is None else centre + rotation @ camera.position
    lnm, valid, pix = _camera_rays(camera)
    H, W = valid.shape
    dirs = lnm[valid] @ rotation.T
    inst_v, t_v, face_v = scene.cast(position, dirs)
    if np.any(inst_v < 0):
        raise RuntimeError("a ray left the room: the scene's mesh is not closed")
    inst = np.full((H, W), -1, np.int32)
    inst[valid] = inst_v
    depth = np.zeros((H, W), np.float32)
    depth[valid] = t_v
    rgb = np.zeros((H, W, 3), np.float32)
    rgb[valid] = shade(scene, position, dirs, inst_v, t_v, face_v, pix[valid])
    edge = edge_pixels(inst, valid)
    if edge.any():  # 2 x 2 supersampling where an object's edge crosses the pixel
        i, j = np.nonzero(edge)
        acc, cnt = np.zeros((len(i), 3)), np.zeros(len(i))
        for du, dv in ((-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25), (0.25, 0.25)):
            r, ok = camera.unproject(np.stack([j + du, i + dv], -1).astype(np.float64))
            if not ok.any():
                continue
            d = normalize(r[ok] @ camera.rotation.T @ rotation.T)
            si, st, sf = scene.cast(position, d)
            hit = si >= 0
            col = np.zeros((ok.sum(), 3))
            col[hit] = shade(scene, position, d[hit], si[hit], st[hit], sf[hit], pix[i[ok], j[ok]][hit])
            acc[ok] += np.where(hit[:, None], col, 0)
            cnt[ok] += hit
        has = cnt > 0
        rgb[i[has], j[has]] = acc[has] / cnt[has, None]
    label = np.full((H, W), IGNORE, np.uint8)
    label[valid] = scene.semantic[inst_v]
    if boxes:
        wb, wc, wi, rays = world_boxes(scene, centre)
        keep = np.array([camera.sees(r @ rotation)[1].mean() >= MIN_VISIBLE_FRACTION for r in rays], bool)
        vb = rotate_boxes(wb[keep], rotation.T) if keep.any() else np.zeros((0, 5))
        bc, bi = wc[keep] if len(wc) else wc, wi[keep] if len(wi) else wi
    else:
        vb, bc, bi = np.zeros((0, 5)), np.zeros(0, np.int64), np.zeros(0, np.int64)
    return View(np.round(rgb * 255).astype(np.uint8), label, inst, depth, valid, vb, bc, bi,
                position, rotation)
