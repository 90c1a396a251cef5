"""Procedural indoor rooms: layout, meshes, appearance and ray casting with Embree.

A room is an axis-aligned box centred on the origin (floor at z = 0) holding structure
(floor, ceiling, walls, beams, columns), wall items (doors, windows, boards, pictures),
furniture yaw-rotated on the floor, and clutter on tables and on the floor. Objects are
placed by rejection sampling on their bounding boxes, so no two intersect. Scene ``index``
of ``seed`` is drawn from ``numpy.random.default_rng([seed, index])``: the same on every
machine.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
import trimesh

from ..geometry import rotation_from_axis_angle
from .classes import DETECTION_CLASSES, semantic_index
from .materials import appearance, check_materials
from .objects import AGAINST_WALL, FLOOR, ON_TABLE, ON_WALL, box, cylinder

WALL_RANGE, HEIGHT_RANGE = (3.0, 9.0), (2.5, 3.5)
#: Changes whenever :func:`make_room` builds other rooms than before, so that datasets
#: rendered and stored before are not read as today's (2, session 71: beds are placed).
ROOMS_VERSION = 2
CAMERA_HEIGHT = (1.2, 1.7)
_FLOOR_MIX = ("table", "table", "chair", "chair", "chair", "sofa", "bed", "bookcase",
              "bookcase", "cabinet", "cabinet", "floor_lamp", "floor_clutter", "floor_clutter")


@dataclass(frozen=True)
class Instance:
    """One object of a scene: what it is and where (its world bounding box)."""

    kind: str
    semantic: int
    detect: int | None
    lo: np.ndarray
    hi: np.ndarray


#: Whether this process has cast a ray: Embree's thread pool then exists, and a process
#: forked from this one would wait on it forever (:func:`embree_started`).
_EMBREE_STARTED = False


def embree_started() -> bool:
    """Whether this process has started Embree (cast a ray): after that, worker processes
    must not be forked from it (a forked worker's Embree waits forever on the threads that
    stayed behind)."""
    return _EMBREE_STARTED


@dataclass(frozen=True)
class Scene:
    """A room: its mesh (faces tagged with instance ids), instances and appearance.

    Use :func:`make_room` to build one, :meth:`viewpoint` for seeded camera poses and
    :func:`usf_graph.scenes.render` to see it through a camera. Read-only: make_room hands
    the same scene to every call with the same arguments, so its fields cannot be set and
    its arrays cannot be written (its mesh is trimesh's: leave it as it is).
    """

    size: tuple
    instances: list
    mesh: trimesh.Trimesh
    face_instance: np.ndarray
    light: np.ndarray
    ambient: float
    appearance: dict
    seed: int = 0
    index: int = 0
    _caster: object = field(default=None, repr=False)
    _boxes: dict = field(default_factory=dict, repr=False)

    @property
    def semantic(self) -> np.ndarray:
        """Semantic label of each instance ``[I]``."""
        return np.array([i.semantic for i in self.instances], np.int64)

    def cast(self, origin, directions):
        """First hits of rays from ``origin`` along ``directions [M, 3]``: instance ids
        ``[M]`` (-1 for a miss), distances ``[M]`` (metres) and face ids ``[M]``."""
        if self._caster is None:
            from trimesh.ray.ray_pyembree import RayMeshIntersector

            global _EMBREE_STARTED
            _EMBREE_STARTED = True
            # the one thing a scene learns after it is built (frozen: set past the guard)
            object.__setattr__(self, "_caster", RayMeshIntersector(self.mesh, scale_to_box=False))
        d = np.ascontiguousarray(directions, np.float64).reshape(-1, 3)
        o = np.broadcast_to(np.asarray(origin, np.float64), d.shape)
        face = self._caster.intersects_first(o, d) if len(d) else np.zeros(0, np.int64)
        hit = face >= 0
        f = np.where(hit, face, 0)
        n = self.mesh.face_normals[f]
        v0 = self.mesh.vertices[self.mesh.faces[f, 0]]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((v0 - o) * n).sum(-1) / (d * n).sum(-1)
        inst = np.where(hit, self.face_instance[f], -1)
        return inst, np.where(hit, t, np.inf), np.where(hit, face, -1)

    def check_viewpoint(self, position) -> np.ndarray:
        """``position`` as a float array, or a clear error when it is outside the room or
        inside an object's bounding box."""
        p = np.asarray(position, np.float64)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(f"a camera position is 3 finite numbers (x, y, z in metres), got {position}")
        half = np.array([self.size[0] / 2, self.size[1] / 2])
        if np.any(np.abs(p[:2]) >= half) or not 0 < p[2] < self.size[2]:
            raise ValueError(
                f"camera position {np.round(p, 3).tolist()} is outside the room: x and y must lie "
                f"within +-{half.round(3).tolist()} and z within (0, {self.size[2]:.3f}) metres")
        for k, inst in enumerate(self.instances):
            if inst.kind != "structure" and np.all(p >= inst.lo) and np.all(p <= inst.hi):
                raise ValueError(f"camera position {np.round(p, 3).tolist()} is inside object {k} "
                                 f"({inst.kind}, bounds {np.round(inst.lo, 2).tolist()} to "
                                 f"{np.round(inst.hi, 2).tolist()}); move it or use scene.viewpoint()")
        return p

    def viewpoint(self, k: int = 0):
        """Seeded camera pose ``k``: a free position at 1.2-1.7 m and a gravity-aligned
        rotation (world <- view) with random yaw."""
        rng = np.random.default_rng([self.seed, self.index, 1_000_003, int(k)])
        half = np.array(self.size[:2]) / 2 - 0.3
        for _ in range(1000):
            p = np.r_[rng.uniform(-half, half), rng.uniform(*CAMERA_HEIGHT)]
            if all(inst.kind == "structure" or np.any(p < inst.lo - 0.15) or np.any(p > inst.hi + 0.15)
                   for inst in self.instances):
                return p, rotation_from_axis_angle([0.0, 0.0, 1.0], rng.uniform(-math.pi, math.pi))
        raise RuntimeError(f"no free camera position in scene {self.index} of seed {self.seed}")


class _Layout:
    """Collects meshes and instances while placing them without overlaps."""

    def __init__(self, rng, size):
        self.rng, self.size = rng, size
        self.meshes, self.owner, self.instances = [], [], []
        self.reserved = []  # space kept free that no object occupies (in front of doors)

    def free(self, lo, hi, ignore=()) -> bool:
        boxes = [(i.lo, i.hi) for k, i in enumerate(self.instances)
                 if i.kind != "structure" and k not in ignore] + self.reserved
        return not any(np.all(np.minimum(hi, h) - np.maximum(lo, l) > 1e-6) for l, h in boxes)

    def add(self, kind, semantic, detect, parts, T=None, check=True, ignore=()) -> int | None:
        lo, hi = _bounds(parts, T)
        half = np.array([self.size[0] / 2, self.size[1] / 2, self.size[2]])
        if check and (np.any(lo[:2] < -half[:2] - 1e-6) or np.any(hi > half + 1e-6)
                      or not self.free(lo, hi, ignore)):
            return None
        m = trimesh.util.concatenate(parts)  # built only once placed: most tries are refused
        if T is not None:
            m.apply_transform(T)
        self.meshes.append(m)
        self.owner.append(np.full(len(m.faces), len(self.instances)))
        det = None if detect is None else DETECTION_CLASSES.index(detect)
        self.instances.append(Instance(kind, semantic_index(semantic), det, lo, hi))
        return len(self.instances) - 1


def _bounds(parts, T=None) -> tuple[np.ndarray, np.ndarray]:
    """The bounds ``(lo, hi)`` of ``parts`` moved by ``T``: to the bit those of the
    concatenated, transformed mesh (the same points through trimesh's own transform),
    without building it (building meshes took half of a room's time)."""
    v = np.vstack([p.vertices for p in parts])
    if T is not None:
        v = trimesh.transformations.transform_points(v, T)
    return v.min(axis=0), v.max(axis=0)


def _extents(parts) -> np.ndarray:
    lo, hi = _bounds(parts)
    return hi - lo


def _pose(yaw, xyz):
    T = np.eye(4)
    T[:3, :3] = rotation_from_axis_angle([0.0, 0.0, 1.0], yaw)
    T[:3, 3] = xyz
    return T


# Walls: (outward normal angle, length axis). Object frames have +y into the wall.
_WALLS = ((-math.pi / 2, 0), (0.0, 1), (math.pi / 2, 0), (math.pi, 1))


def _wall_pose(size, wall, s, depth):
    """Pose of an object whose back touches ``wall`` at position ``s`` along it (2 mm off):
    ``depth`` is the back's y in the object's frame (0 for wall items)."""
    ang, _ = _WALLS[wall]
    out = np.array([math.cos(ang), math.sin(ang)])
    half = np.array(size[:2]) / 2
    centre = out * (np.abs(out) @ half - depth - 0.002)
    along = np.array([-out[1], out[0]])
    return _pose(ang - math.pi / 2, np.r_[centre + along * s, 0.0])


def _structure(lay, L, W, H):
    quads = {"floor": ([-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]),
             "ceiling": ([-1, -1, 1], [-1, 1, 1], [1, 1, 1], [1, -1, 1])}
    for name, q in quads.items():
        v = np.array(q, float) * [L / 2, W / 2, H]
        lay.add("structure", name, None, [trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)],
                check=False)
    corners = np.array([[-L / 2, -W / 2], [L / 2, -W / 2], [L / 2, W / 2], [-L / 2, W / 2]])
    for k in range(4):
        a, b = corners[k], corners[(k + 1) % 4]
        v = np.array([[*a, 0], [*b, 0], [*b, H], [*a, H]])
        lay.add("structure", "wall", None, [trimesh.Trimesh(v, [[0, 2, 1], [0, 3, 2]], process=False)],
                check=False)


def _columns_and_beams(lay, L, W, H):
    rng = lay.rng
    for _ in range(rng.integers(0, 3) if rng.random() < 0.6 else 0):
        wall = int(rng.integers(4))
        length = (L, W)[_WALLS[wall][1]]
        w, d = rng.uniform(0.3, 0.6), rng.uniform(0.3, 0.6)
        s = rng.choice([-1, 1]) * (length / 2 - w / 2) if rng.random() < 0.5 else \
            rng.uniform(-length / 2 + w, length / 2 - w)
        lay.add("column", "column", None, [box((w, d, H), (0, 0, H / 2))],
                _wall_pose(lay.size, wall, s, d / 2))
    for _ in range(rng.integers(1, 3) if rng.random() < 0.5 else 0):
        w, d = rng.uniform(0.2, 0.4), rng.uniform(0.2, 0.4)
        if rng.random() < 0.5:
            y = rng.uniform(-W / 2 + 0.5, W / 2 - 0.5)
            part = box((L, w, d), (0, y, H - d / 2))
        else:
            x = rng.uniform(-L / 2 + 0.5, L / 2 - 0.5)
            part = box((w, W, d), (x, 0, H - d / 2))
        lay.add("beam", "beam", None, [part])


def _wall_items(lay, L, W, H):
    rng = lay.rng
    counts = {"door": rng.integers(1, 3), "window": rng.integers(0, 4), "board": rng.integers(0, 3),
              "picture": rng.integers(0, 5)}
    for kind, n in counts.items():
        t = ON_WALL[kind]
        for _ in range(int(n)):
            for _attempt in range(30):
                wall = int(rng.integers(4))
                length = (L, W)[_WALLS[wall][1]]
                parts = t.build(rng)
                ext = _extents(parts)
                if ext[0] > length - 0.4:
                    continue
                s = rng.uniform(-length / 2 + ext[0] / 2 + 0.1, length / 2 - ext[0] / 2 - 0.1)
                T = _wall_pose(lay.size, wall, s, 0.0)
                if kind == "door":  # keep the floor in front of a door free
                    clear = box((ext[0] + 0.2, 0.9, 2.0), (0, -0.5, 1.0))
                    lo, hi = _bounds([clear], T)
                    if not lay.free(lo, hi):
                        continue
                    if lay.add(kind, t.semantic, t.detect, parts, T) is not None:
                        lay.reserved.append((lo, hi))
                        break
                elif lay.add(kind, t.semantic, t.detect, parts, T) is not None:
                    break


def _furniture(lay, L, W, n):
    rng = lay.rng
    tables = []
    for _ in range(n):
        kind = _FLOOR_MIX[int(rng.integers(len(_FLOOR_MIX)))]
        t = FLOOR[kind]
        for _attempt in range(40):
            parts = t.build(rng)
            lo, hi = _bounds(parts)
            ext = hi - lo
            if kind in AGAINST_WALL:
                wall = int(rng.integers(4))
                length = (L, W)[_WALLS[wall][1]]
                if ext[0] > length - 0.2:
                    continue
                s = rng.uniform(-length / 2 + ext[0] / 2, length / 2 - ext[0] / 2)
                # the back (max y), not half the depth: a bed's headboard and a cabinet's
                # handle make their footprints off-centre in y (beds went into the wall)
                T = _wall_pose(lay.size, wall, s, hi[1])
            else:
                xy = rng.uniform(-1, 1, 2) * (np.array([L, W]) / 2 - 0.3)
                T = _pose(rng.uniform(-math.pi, math.pi), np.r_[xy, 0.0])
            k = lay.add(kind, t.semantic, t.detect, parts, T)
            if k is not None:
                if kind == "table":
                    tables.append((k, T, ext))
                break
    for k, T, ext in tables:  # clutter on table tops: checked against each other only
        for _ in range(int(rng.integers(0, 5))):
            kind = ("cup", "bottle", "book")[int(rng.integers(3))]
            t = ON_TABLE[kind]
            for _attempt in range(20):
                parts = t.build(rng)
                e = _extents(parts)
                xy = rng.uniform(-1, 1, 2) * np.maximum((ext[:2] - e[:2].max()) / 2 - 0.03, 0)
                Tc = T @ _pose(rng.uniform(-math.pi, math.pi), np.r_[xy, ext[2]])
                if lay.add(kind, t.semantic, t.detect, parts, Tc, ignore=[k]) is not None:
                    break


#: How many rooms :func:`make_room` keeps (a few MB each, with their cast boxes), for
#: code that asks for the same rooms again (the tests spent 83% of their room building on
#: rooms built before); a protocol's 50 test rooms per lens are more than it keeps.
ROOMS_KEPT = 16


def make_room(seed: int = 0, index: int = 0, size=None, num_objects: int | None = None,
              materials: str = "random") -> Scene:
    """Build room ``index`` of ``seed``: the same :class:`Scene` (read-only) for the same
    arguments, the last :data:`ROOMS_KEPT` of them kept.

    Args:
        seed, index: the room is drawn from ``numpy.random.default_rng([seed, index])``.
        size: ``(length, width, height)`` in metres; random (walls 3-9 m, height 2.5-3.5 m)
            when None.
        num_objects: how many pieces of furniture to try to place (random 4-12 when None).
        materials: ``"random"`` (every object's look drawn at random: the protocols' rooms)
            or ``"by_kind"`` (a material per kind of object, as in real rooms; the same
            layout and light), :mod:`usf_graph.scenes.materials`.
    """
    check_materials(materials)
    if size is not None:
        size = tuple(float(s) for s in size)
    return _room(int(seed), int(index), size, None if num_objects is None else int(num_objects),
                 materials)


def _read_only(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


@functools.lru_cache(maxsize=ROOMS_KEPT)
def _room(seed: int, index: int, size, num_objects, materials: str) -> Scene:
    rng = np.random.default_rng([seed, index])
    if size is None:
        size = (*rng.uniform(*WALL_RANGE, 2), rng.uniform(*HEIGHT_RANGE))
    size = tuple(float(s) for s in size)
    if len(size) != 3 or not all(math.isfinite(s) and s > 0 for s in size):
        raise ValueError(f"room size must be three positive lengths (length, width, height) in "
                         f"metres, got {size}")
    if min(size[:2]) < 1.5 or size[2] < 2.0:
        raise ValueError(f"room size {size} is too small: walls need at least 1.5 m and the height "
                         f"2.0 m to hold a camera at 1.2-1.7 m")
    L, W, H = size
    lay = _Layout(rng, size)
    _structure(lay, L, W, H)
    _columns_and_beams(lay, L, W, H)
    _wall_items(lay, L, W, H)
    _furniture(lay, L, W, int(rng.integers(4, 13)) if num_objects is None else num_objects)
    for _ in range(int(rng.integers(1, 3))):
        r = rng.uniform(0.2, 0.3)
        xy = rng.uniform(-1, 1, 2) * (np.array([L, W]) / 2 - 0.5)
        lay.add("ceiling_light", "clutter", "light", [cylinder(r, 0.06, (*xy, H - 0.03), 24)])
    mesh = trimesh.util.concatenate(lay.meshes)
    ap = appearance(lay.instances, rng, materials, (seed, index))
    light = np.array([*rng.uniform(-0.3, 0.3, 2) * [L, W], H - 0.25])
    for a in [*(i.lo for i in lay.instances), *(i.hi for i in lay.instances), *ap.values()]:
        _read_only(a)
    return Scene(size, tuple(lay.instances), mesh, _read_only(np.concatenate(lay.owner)),
                 _read_only(light), float(rng.uniform(0.3, 0.45)), ap, seed, index)
