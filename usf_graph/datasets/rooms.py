r"""PyG datasets of procedural rooms (:mod:`usf_graph.scenes`) seen through any camera.

Each sample is one view: the RGB image lifted to a grid as ``x``, the exact label of every
grid point as ``y`` (from a ray cast along the point's direction, not from the image), the
camera's field-of-view ``mask``, and for detection the view's spherical boxes. The raw
image and its per-pixel labels are kept too, for planar baselines.

Training and test rooms never overlap: the test split uses the rooms of ``seed + 1``.
Views are gravity-aligned with random yaw (``rotate="none"``) or turned by a Haar-random
rotation (``rotate="so3"``), both seeded, so a test set is the same in every run and for
every camera: the same viewpoints seen through another lens give a zero-shot test.
"""

from __future__ import annotations

import numpy as np
import torch
from torch_geometric.data import Dataset
from tqdm.auto import tqdm

from ..cameras import Camera, Equirectangular
from ..fileio import atomic_torch_save
from ..frontend import SphericalFrontend
from ..frontend.image import SphericalImage
from ..geometry import random_rotation
from ..grids import Grid, from_spec
from ..scenes import IGNORE, make_room, render
from ..scenes.materials import check_materials
from ..scenes.room import ROOMS_VERSION, embree_started
from .stacked import add_boxes, load_or_rebuild, pack_boxes, pre_transform_stacked

ROTATIONS = ("none", "so3")
#: The rooms of :class:`RoomsGravity`'s extra panoramas, shared with no protocol split.
GRAVITY_SEED = 1000


def split_seed(split: str, seed: int) -> int:
    """The seed of a split's rooms: ``seed`` for ``train``, ``seed + 1`` for ``test``. So
    the training rooms of seed ``s + 1`` are the test rooms of seed ``s``: score a model
    on the test rooms of its own seed."""
    return seed + (0 if split == "train" else 1)


def _check_rotate(rotate: str) -> None:
    if rotate not in ROTATIONS:
        raise ValueError(f"rotate must be one of {ROTATIONS}, got {rotate!r}")


def _haar(sample: int, seed: int) -> np.ndarray:
    return random_rotation(seed=(seed * 1_000_003 + sample) % 2**62).numpy()


def view_pose(scene, rotate: str, sample: int, seed: int):
    """Position and rotation (world <- view) of a sample under a rotation protocol."""
    _check_rotate(rotate)
    p, R = scene.viewpoint(0)
    if rotate == "so3":
        R = _haar(sample, seed)
    return p, R


def view_up(rotate: str, sample: int, seed: int) -> np.ndarray:
    r"""Gravity's up direction (world +z) in the frame of the view :func:`view_pose` gives,
    ``[3]``: +z for gravity-aligned views (their yaw leaves it), :math:`R^\top e_z` for
    the rotated ones; what an IMU on the camera would report."""
    _check_rotate(rotate)
    return _haar(sample, seed)[2].copy() if rotate == "so3" else np.array([0.0, 0.0, 1.0])


def grid_labels(scene, position, rotation, pos: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Exact semantic label of each grid point ``pos [N, 3]`` (view frame) seen from
    ``position``; :data:`~usf_graph.scenes.IGNORE` where ``mask`` is False."""
    y = np.full(len(pos), IGNORE, np.int64)
    inst, _, _ = scene.cast(position, pos[mask] @ rotation.T)
    y[mask] = scene.semantic[inst]
    return y


#: Environment variable: processes that render a split's views (1: this process alone).
WORKERS_ENV = "USF_GRAPH_RENDER_WORKERS"


def render_workers(num_views: int) -> int:
    """How many processes render ``num_views`` views: ``$USF_GRAPH_RENDER_WORKERS`` when
    set, else up to 8 (the machine's cores) for 32 views or more and 1 below, where
    starting processes would cost more than it saves. Each view depends only on its seed
    and index, so the views are the same whatever the number."""
    import os

    raw = os.environ.get(WORKERS_ENV)
    if raw is not None:
        if not raw.strip().isdigit() or int(raw) < 1:
            raise ValueError(f"{WORKERS_ENV} must be a whole number of processes >= 1, got "
                             f"{raw!r}; unset it to use the machine's cores")
        return int(raw)
    return min(8, os.cpu_count() or 1) if num_views >= 32 else 1


class _ViewJob:
    """Renders view ``i`` of a split (a picklable callable, for worker processes):
    the room, the image, and the exact labels of the grid points when ``pos`` is given."""

    def __init__(self, seed: int, rotate: str, camera: Camera, boxes: bool,
                 pos: np.ndarray | None = None, mask: np.ndarray | None = None,
                 materials: str = "random"):
        self.seed, self.rotate, self.camera, self.boxes = seed, rotate, camera, boxes
        self.pos, self.mask, self.materials = pos, mask, materials

    def __call__(self, i: int):
        scene = make_room(self.seed, i, materials=self.materials)
        p, R = view_pose(scene, self.rotate, i, self.seed)
        view = render(scene, self.camera, position=p, rotation=R, boxes=self.boxes)
        y = None if self.pos is None else grid_labels(scene, p, R, self.pos, self.mask)
        return view, y


def _single_threaded() -> None:
    torch.set_num_threads(1)  # a worker is one of several processes: no oversubscription


def worker_start_method() -> str:
    """How :func:`render_views` starts its workers on Linux: forked, as PyTorch's
    DataLoader does, while this process has not cast a ray; spawned once it has
    (:func:`~usf_graph.scenes.room.embree_started`), because a forked worker's Embree would
    wait forever on a thread pool that stayed behind. (A spawned worker imports the main
    module again: a script that renders rooms needs ``if __name__ == "__main__":``, or
    Python stops it with its bootstrapping error.)"""
    return "spawn" if embree_started() else "fork"


def render_views(job: _ViewJob, n: int, desc: str, progress: bool):
    """``job(i)`` for ``i`` in ``range(n)``, in order, in :func:`render_workers` processes
    started by :func:`worker_start_method` on Linux (elsewhere fork is unsafe with some
    system libraries and spawn would rerun an unguarded script, so all here), with a
    progress bar."""
    import multiprocessing
    import sys

    workers = min(render_workers(n), n)
    if workers > 1 and sys.platform.startswith("linux"):
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(workers, multiprocessing.get_context(worker_start_method()),
                                 initializer=_single_threaded) as pool:
            yield from tqdm(pool.map(job, range(n), chunksize=max(1, n // (8 * workers))),
                            total=n, desc=desc, disable=not progress, leave=False)
        return
    yield from tqdm(map(job, range(n)), total=n, desc=desc, disable=not progress, leave=False)


def _cache_stem(prefix: str, materials: str = "random", **key) -> str:
    """A processed file's name, less its extension, that changes with everything the
    rendering depends on: the rooms' version (:data:`~usf_graph.scenes.room.ROOMS_VERSION`)
    and ``materials``, named only where not the default."""
    import hashlib
    import json

    if materials != "random":
        key["materials"] = materials
    key["rooms"] = ROOMS_VERSION
    return f"{prefix}_{hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:12]}"


class _Rendered(Dataset):
    """A dataset rendered here: there are no raw files and nothing to download."""

    @property
    def raw_file_names(self):
        return []

    def download(self):
        pass


class _Rooms(_Rendered):
    """Renders, lifts and stores a split once under ``root/processed``; loads it after."""

    renders_boxes = True  # whether views list their objects' boxes (about 60% of a render's time)

    def __init__(self, root, split: str = "train", camera: Camera | None = None,
                 grid="icosahedral:5", num_scenes: int | None = None, rotate: str = "none",
                 seed: int = 0, interpolation: str = "bilinear", transform=None,
                 pre_transform=None, progress: bool = True, materials: str = "random"):
        if split not in ("train", "test"):
            raise ValueError(f"split must be 'train' or 'test', got {split!r}")
        _check_rotate(rotate)
        self.split, self.rotate, self.seed = split, rotate, int(seed)
        self.materials = check_materials(materials)
        self.camera = Equirectangular(256, 128) if camera is None else camera
        self.grid: Grid = from_spec(grid) if isinstance(grid, str) else grid
        self.num_scenes = int(num_scenes if num_scenes is not None else (200 if split == "train" else 50))
        if self.num_scenes < 1:
            raise ValueError(f"num_scenes must be at least 1, got {num_scenes}")
        self.interpolation, self.progress = interpolation, progress
        self.frontend = SphericalFrontend(self.camera, self.grid, interpolation=interpolation)
        super().__init__(str(root), transform, pre_transform, log=False)
        self._load()

    # -- storage -------------------------------------------------------------------
    @property
    def processed_file_names(self):
        no_boxes = {} if self.renders_boxes else {"boxes": False}  # a split with boxes keeps its name
        return [_cache_stem(f"rooms_{self.split}_{self.rotate}_s{self.seed}", camera=self.camera.key(),
                            grid=self.grid.spec, interp=self.interpolation, n=self.num_scenes,
                            materials=self.materials, **no_boxes) + ".pt"]

    def _load(self):
        blob = load_or_rebuild(self.processed_paths[0], self.process,
                               ("x", "y", "mask", "image", "label_image", "boxes", "box_class", "box_ptr"))
        for k, v in blob.items():
            setattr(self, k, v)

    @property
    def scene_seed(self) -> int:
        """The seed of the split's rooms (:func:`split_seed`)."""
        return split_seed(self.split, self.seed)

    @property
    def gravity(self) -> torch.Tensor:
        """Every view's up direction in its own frame, ``[S, 3]`` float64
        (:func:`view_up`): the known gravity of an IMU, for models that read one."""
        if getattr(self, "_gravity", None) is None:
            self._gravity = torch.as_tensor(np.stack(
                [view_up(self.rotate, i, self.scene_seed) for i in range(self.len())]))
        return self._gravity

    def process(self):
        scene_seed = self.scene_seed
        pos, mask = self.grid.pos.numpy(), self.frontend.mask.numpy()
        xs, ys, masks, imgs, labs, boxes, classes = [], [], [], [], [], [], []
        job = _ViewJob(scene_seed, self.rotate, self.camera, self.renders_boxes, pos, mask,
                       self.materials)
        for view, y in render_views(job, self.num_scenes, f"rendering {self.split} rooms",
                                    self.progress):
            xs.append(self.frontend.lift(view.rgb.astype(np.float32) / 255))
            ys.append(y)
            masks.append(mask)
            imgs.append(view.rgb)
            labs.append(view.label)
            boxes.append(view.boxes)
            classes.append(view.box_class)
        x = torch.stack(xs).to(torch.float16)
        y = torch.as_tensor(np.stack(ys))
        if self.pre_transform is not None:
            x = pre_transform_stacked(
                self.pre_transform, (self._sample(xi.float(), y[i], i) for i, xi in enumerate(x)),
                "x", fixed=("pos",)).to(torch.float16)
        atomic_torch_save({
            "x": x, "y": y, "mask": torch.as_tensor(np.stack(masks)),
            "image": torch.as_tensor(np.stack(imgs)), "label_image": torch.as_tensor(np.stack(labs)),
            **pack_boxes(boxes, classes)}, self.processed_paths[0])

    # -- samples ---------------------------------------------------------------------
    def len(self) -> int:
        return len(self.x)

    def _sample(self, x, y, idx) -> SphericalImage:
        return SphericalImage(x=x, y=y, pos=self.grid.pos.float(), area=self.grid.area.float())

    def get(self, idx: int) -> SphericalImage:
        d = self._sample(self.x[idx].float(), self.y[idx], idx)
        d.mask = self.mask[idx]
        d.image = self.image[idx][None]
        d.label_image = self.label_image[idx][None]
        d.up = self.gravity[idx].float()[None]
        return d

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({len(self)}, split={self.split}, rotate={self.rotate}, "
                f"camera={self.camera!r}, grid={self.grid.spec})")


class RoomsSegmentation(_Rooms):
    r"""Semantic segmentation of procedural rooms, a PyG dataset (13 Stanford 2D-3D-S classes).

    Args:
        root: where the rendered split is stored (one file, written atomically; an
            unreadable file is rendered again).
        split: ``train`` (rooms of ``seed``) or ``test`` (rooms of ``seed + 1``).
        camera: any :mod:`usf_graph.cameras` model (default ``Equirectangular(256, 128)``).
        grid: grid spec or :class:`~usf_graph.grids.Grid` the image is lifted to.
        num_scenes: number of rooms, one view each (200 for train, 50 for test by default).
        rotate: ``none`` (gravity-aligned, random yaw) or ``so3`` (Haar, seeded per view).
        seed: seed of the rooms and rotations.
        interpolation, transform, pre_transform, progress: the lift's interpolation, PyG's
            transforms, a progress bar while rendering.
        materials: ``"random"`` (the protocols' rooms) or ``"by_kind"`` (a material per kind
            of object; :mod:`usf_graph.scenes.materials`).

    A sample has ``x [N, 3]`` (RGB in [0, 1], 0 outside the field of view), ``y [N]``
    (class index, 255 = ignore outside the field of view), ``mask [N]``, ``pos``, ``area``,
    and the camera's ``image [1, H, W, 3]`` uint8 and ``label_image [1, H, W]``. The whole
    split is also in static-graph form: ``dataset.x [S, N, 3]`` (float16), ``dataset.y``,
    ``dataset.mask``, ``dataset.image``, ``dataset.label_image``.
    """

    renders_boxes = False  # segmentation reads no boxes, and a render is 2.5x faster without them


class RoomsDetection(_Rooms):
    r"""Spherical-box detection in procedural rooms, a PyG dataset.

    The same arguments and fields as :class:`RoomsSegmentation`, plus ``boxes [K, 5]``
    (``[lon, lat, fov_x, fov_y, roll]`` in radians, the view's frame; see
    :mod:`usf_graph.ops.boxes`) and ``box_class [K]`` (index into
    :data:`usf_graph.scenes.DETECTION_CLASSES`). Batch them with PyG's
    ``DataLoader(..., follow_batch=["boxes"])`` to get ``boxes_batch``. A view lists an
    object when its visible part covers at least
    :data:`usf_graph.scenes.render.MIN_SOLID_ANGLE` sr and the camera sees at least
    :data:`~usf_graph.scenes.render.MIN_VISIBLE_FRACTION` of it.
    """

    def get(self, idx: int) -> SphericalImage:
        return add_boxes(super().get(idx), self, idx)


class RoomsGravity(_Rendered):
    r"""Upright panoramas of procedural rooms that carry only their signal and gravity: cheap
    extra views for training an up estimate (:func:`~usf_graph.train.gravity.pretrain_up`),
    which needs many more rooms than a segmenter or a detector does (README).

    No labels, boxes or raw images are made, which makes a view about 2.5x cheaper to
    render than a :class:`RoomsSegmentation` one (about 0.08 s on one core). The rooms are
    those of ``seed`` (by default 1000, shared with no protocol split). A sample has ``x [N,
    3]``, ``pos``, ``area``, ``mask [N]`` and ``up [1, 3]`` (+z: the views are
    gravity-aligned with random yaw); ``dataset.x [S, N, 3]`` (float16) holds the split.
    ``materials`` as in :class:`RoomsSegmentation`.
    """

    def __init__(self, root, num_scenes: int, camera: Camera | None = None,
                 grid="icosahedral:5", seed: int = GRAVITY_SEED, progress: bool = True,
                 materials: str = "random"):
        if num_scenes < 1:
            raise ValueError(f"num_scenes must be at least 1, got {num_scenes}")
        self.num_scenes, self.seed, self.progress = int(num_scenes), int(seed), progress
        self.materials = check_materials(materials)
        self.camera = Equirectangular(192, 96) if camera is None else camera
        self.grid: Grid = from_spec(grid) if isinstance(grid, str) else grid
        self.frontend = SphericalFrontend(self.camera, self.grid)
        super().__init__(str(root), log=False)
        blob = load_or_rebuild(self.processed_paths[0], self.process, ("x",))
        self.x = blob["x"]

    @property
    def _stem(self) -> str:
        return _cache_stem(f"rooms_gravity_s{self.seed}", camera=self.camera.key(), grid=self.grid.spec,
                           materials=self.materials)

    @property
    def processed_file_names(self):
        return [f"{self._stem}_n{self.num_scenes}.pt"]

    def process(self):
        x = self._from_larger_split()
        atomic_torch_save({"x": self._render() if x is None else x}, self.processed_paths[0])

    def _render(self) -> torch.Tensor:
        """Every view rendered and lifted, ``[num_scenes, N, 3]`` float16."""
        job = _ViewJob(self.seed, "none", self.camera, boxes=False, materials=self.materials)
        views = render_views(job, self.num_scenes, "rendering rooms for the up estimate",
                             self.progress)
        return torch.stack([self.frontend.lift(view.rgb.astype(np.float32) / 255)
                            for view, _ in views]).to(torch.float16)

    def _from_larger_split(self) -> torch.Tensor | None:
        """The first views of a larger stored split of the same seed, camera and grid (view
        i depends on the seed and i only; e.g. the segmentation protocol's 800 after the
        detection protocol's 1,600), or ``None``."""
        from pathlib import Path

        for path in sorted(Path(self.processed_dir).glob(f"{self._stem}_n*.pt")):
            n = path.stem.rsplit("_n", 1)[-1]
            if not n.isdigit() or int(n) <= self.num_scenes:
                continue
            try:
                x = torch.load(path, weights_only=True)["x"]
            except Exception:  # noqa: BLE001 - an unreadable file is simply not used
                continue
            if len(x) == int(n):
                return x[:self.num_scenes].clone()
        return None

    def len(self) -> int:
        return len(self.x)

    def get(self, idx: int) -> SphericalImage:
        d = SphericalImage(x=self.x[idx].float(), pos=self.grid.pos.float(), area=self.grid.area.float())
        d.mask = self.frontend.mask.clone()
        d.up = torch.tensor([[0.0, 0.0, 1.0]])
        return d

    def __repr__(self) -> str:
        return f"{type(self).__name__}({len(self)}, camera={self.camera!r}, grid={self.grid.spec})"
