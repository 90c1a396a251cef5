import hashlib
import json

import numpy as np
import pytest
import torch
from torch_geometric.loader import DataLoader

from usf_graph import cameras, scenes
from usf_graph.datasets import RoomsDetection, RoomsGravity, RoomsSegmentation
from usf_graph.datasets.rooms import WORKERS_ENV, render_workers, view_pose, view_up
from usf_graph.scenes import IGNORE, SEMANTIC_CLASSES

KW = dict(num_scenes=3, grid="icosahedral:3", progress=False)
FISHEYE = cameras.KannalaBrandt(90, 90, 127.5, 127.5, 256, 256, k=(0.0, 0.0, 0.0, 0.0)).with_fov(190)


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return tmp_path_factory.mktemp("rooms")


def test_sample_holds_lifted_rgb_exact_labels_and_the_raw_view(root):
    ds = RoomsSegmentation(root, "train", **KW)
    assert len(ds) == 3
    d = ds[1]
    assert d.x.shape == (642, 3) and d.y.shape == (642,) and d.mask.all()
    # x is the camera image lifted through the dataset's frontend
    lifted = ds.frontend.lift(d.image[0].numpy().astype(np.float32) / 255)
    torch.testing.assert_close(d.x, lifted, atol=2e-3, rtol=0)
    # y is the exact label of each point's ray; the nearest pixel agrees away from edges
    uv, _ = ds.camera.sees(ds.grid.pos.numpy())
    j, i = np.rint(uv[:, 0]).astype(int) % 256, np.clip(np.rint(uv[:, 1]), 0, 127).astype(int)
    assert (d.label_image[0].numpy()[i, j] == d.y.numpy()).mean() > 0.93
    scene = scenes.make_room(0, 1)
    p, R = view_pose(scene, "none", 1, 0)
    inst, _, _ = scene.cast(p, ds.grid.pos.numpy() @ R.T)
    assert np.array_equal(d.y.numpy(), scene.semantic[inst])


def test_splits_are_different_rooms_and_reload_from_disk(root):
    a = RoomsSegmentation(root, "train", **KW)
    b = RoomsSegmentation(root, "test", **KW)
    assert not torch.equal(a.x, b.x)
    again = RoomsSegmentation(root, "train", **KW)
    assert torch.equal(a.x, again.x) and torch.equal(a.y, again.y)
    # the test rooms of seed 0 are the training rooms of seed 1, as split_seed says
    shifted = RoomsSegmentation(root, "train", seed=1, **KW)
    assert (b.scene_seed, shifted.scene_seed) == (1, 1) and torch.equal(b.x, shifted.x)


def test_zero_shot_lens_sees_the_same_rotated_test_views(root):
    eq = RoomsSegmentation(root, "test", rotate="so3", **KW)
    fe = RoomsSegmentation(root, "test", rotate="so3", camera=FISHEYE, **KW)
    for k in range(len(eq)):
        m = fe.mask[k]
        assert 0.3 < m.float().mean() < 0.8
        assert (fe.y[k][~m] == IGNORE).all()
        assert torch.equal(fe.y[k][m], eq.y[k][m])  # same pose, same exact labels
    none = RoomsSegmentation(root, "test", **KW)
    assert not torch.equal(none.y, eq.y)


def test_views_know_their_gravity_even_when_rotated(root):
    """Each view's up (an IMU's reading) is world +z in the view's frame: the exact labels
    say ceiling along it and floor against it, rotated or not."""
    for rotate in ("none", "so3"):
        ds = RoomsSegmentation(root, "test", rotate=rotate, **KW)
        g = ds.gravity
        assert g.shape == (3, 3) and g.dtype == torch.float64
        torch.testing.assert_close(g.norm(dim=1), torch.ones(3, dtype=torch.float64))
        pos = ds.grid.pos.double()
        for k in range(len(ds)):
            up, down = (pos @ g[k]).argmax(), (pos @ g[k]).argmin()
            assert SEMANTIC_CLASSES[int(ds.y[k][up])] in ("ceiling", "beam")
            assert SEMANTIC_CLASSES[int(ds.y[k][down])] == "floor"
            torch.testing.assert_close(ds[k].up[0], g[k].float())
            _, R = view_pose(scenes.make_room(1, k), rotate, k, 1)
            np.testing.assert_allclose(R @ view_up(rotate, k, 1), [0, 0, 1], atol=1e-12)
        # a PyG index view, made before anything read the gravity, keeps each sample's own
        sub = RoomsSegmentation(root, "test", rotate=rotate, **KW)[[2, 0]]
        assert torch.equal(sub[0].up[0], g[2].float()) and torch.equal(sub[1].up[0], g[0].float())
        if rotate == "none":
            assert (g == torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)).all()
        else:  # Haar-random: far from +z for some view
            assert float(g[:, 2].min()) < 0.9


def test_detection_boxes_match_a_direct_rendering(root):
    ds = RoomsDetection(root, "train", **KW)
    d = ds[2]
    scene = scenes.make_room(0, 2)
    p, R = view_pose(scene, "none", 2, 0)
    view = scenes.render(scene, ds.camera, position=p, rotation=R)
    torch.testing.assert_close(d.boxes, torch.as_tensor(view.boxes).float())
    assert torch.equal(d.box_class, torch.as_tensor(view.box_class))
    batch = next(iter(DataLoader(ds, batch_size=3, follow_batch=["boxes"])))
    assert batch.boxes_batch.bincount().tolist() == [len(ds[i].boxes) for i in range(3)]


def test_segmentation_splits_skip_boxes_and_never_share_a_detection_file(root):
    """Segmentation renders without boxes (the same images and labels), so it must not
    store its split where a detection split of the same arguments would look."""
    seg, det = RoomsSegmentation(root, "test", **KW), RoomsDetection(root, "test", **KW)
    assert seg.processed_paths != det.processed_paths
    assert torch.equal(seg.x, det.x) and torch.equal(seg.y, det.y)
    assert len(seg.boxes) == 0 and len(det.boxes) > 0 and "boxes" not in seg[0]
    assert len(RoomsDetection(root, "test", **KW).boxes) == len(det.boxes)  # reloaded, boxes intact


def test_corrupt_file_is_rendered_again(root):
    ds = RoomsSegmentation(root, "train", num_scenes=2, grid="icosahedral:2", progress=False)
    path = ds.processed_paths[0]
    with open(path, "wb") as f:
        f.write(b"not a torch file")
    with pytest.warns(UserWarning, match="unreadable"):
        again = RoomsSegmentation(root, "train", num_scenes=2, grid="icosahedral:2", progress=False)
    assert torch.equal(again.y, ds.y)


def test_bad_arguments(root):
    with pytest.raises(ValueError, match="rotate must be one of"):
        RoomsSegmentation(root, rotate="z", **KW)
    with pytest.raises(ValueError, match="split must be"):
        RoomsSegmentation(root, split="val", **KW)
    with pytest.raises(ValueError, match="num_scenes must be at least 1, got 0"):
        RoomsSegmentation(root, **{**KW, "num_scenes": 0})


def test_gravity_views_are_a_train_splits_views_without_labels_or_boxes(root):
    """The cheap up-estimate views render the same images as a train split of their seed
    (the labels and boxes skipped change nothing else), carry +z, and reload from disk;
    the default seed's rooms are not the protocol's."""
    cam = cameras.Equirectangular(64, 32)
    full = RoomsSegmentation(root, "train", camera=cam, seed=7, **KW)
    cheap = RoomsGravity(root, 3, camera=cam, grid="icosahedral:3", seed=7, progress=False)
    assert torch.equal(cheap.x, full.x) and len(cheap) == 3
    s = cheap[1]
    assert torch.equal(s.x, full[1].x) and s.mask.all() and "y" not in s
    assert torch.equal(s.up, torch.tensor([[0.0, 0.0, 1.0]]))
    assert torch.equal(RoomsGravity(root, 3, camera=cam, grid="icosahedral:3", seed=7, progress=False).x,
                       cheap.x)
    other = RoomsGravity(root, 3, camera=cam, grid="icosahedral:3", progress=False)
    train = RoomsSegmentation(root, "train", camera=cam, **KW)
    assert not torch.equal(other.x, train.x)
    with pytest.raises(ValueError, match="num_scenes must be at least 1"):
        RoomsGravity(root, 0)


def test_gravity_views_are_cut_from_a_larger_stored_split(tmp_path, monkeypatch):
    cam = cameras.Equirectangular(64, 32)
    kw = dict(camera=cam, grid="icosahedral:2", progress=False)
    big = RoomsGravity(tmp_path, 4, **kw)
    monkeypatch.setattr("usf_graph.datasets.rooms.render", lambda *a, **k: 1 / 0)  # no rendering
    small = RoomsGravity(tmp_path, 2, **kw)
    assert torch.equal(small.x, big.x[:2]) and small.processed_paths != big.processed_paths
    with pytest.raises(ZeroDivisionError):  # another seed's rooms are not cut from it
        RoomsGravity(tmp_path, 2, seed=3, **kw)


def test_splits_rendered_by_worker_processes_equal_those_rendered_here(tmp_path, monkeypatch):
    """Each view depends only on its seed and index, so two worker processes store the
    same split and boxes as this process alone (the up views go through the same
    ``render_views``: a third pool added 10 s); a worker's error reaches here.
    This process casts rays first, so the workers are spawned: forked, they waited forever
    on Embree's thread pool (session 57's suite hung here)."""
    from usf_graph.datasets import rooms

    cam = cameras.Equirectangular(64, 32)
    kw = dict(camera=cam, num_scenes=5, grid="icosahedral:2", progress=False)
    monkeypatch.setenv(WORKERS_ENV, "1")
    alone = RoomsDetection(tmp_path / "alone", **kw)
    assert rooms.worker_start_method() == "spawn"
    monkeypatch.setenv(WORKERS_ENV, "2")
    assert render_workers(5) == 2
    two = RoomsDetection(tmp_path / "two", **kw)
    for k in ("x", "y", "mask", "image", "label_image", "boxes", "box_class", "box_ptr"):
        assert torch.equal(getattr(alone, k), getattr(two, k)), k
    # forked workers (this process as if it had cast no ray) take the broken render along
    monkeypatch.setattr("usf_graph.scenes.room._EMBREE_STARTED", False)
    assert rooms.worker_start_method() == "fork"
    monkeypatch.setattr("usf_graph.datasets.rooms.render", lambda *a, **k: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        RoomsSegmentation(tmp_path / "broken", **kw)


def test_render_workers_reads_its_variable_and_names_a_bad_value(monkeypatch):
    import os

    monkeypatch.delenv(WORKERS_ENV, raising=False)
    assert render_workers(31) == 1
    assert render_workers(32) == min(8, os.cpu_count() or 1)
    monkeypatch.setenv(WORKERS_ENV, "3")
    assert render_workers(1) == 3
    for bad in ("0", "two", "-1", ""):
        monkeypatch.setenv(WORKERS_ENV, bad)
        with pytest.raises(ValueError, match=f"{WORKERS_ENV} must be a whole number"):
            render_workers(100)


def test_rooms_by_kind_and_rooms_of_another_version_are_stored_apart(tmp_path, monkeypatch):
    from usf_graph.datasets import rooms
    from usf_graph.datasets.rooms import _cache_stem

    assert _cache_stem("p", n=3) == _cache_stem("p", materials="random", n=3)
    # the default names no materials, so splits stored before they existed still load
    plain = json.dumps({"n": 3, "rooms": rooms.ROOMS_VERSION}, sort_keys=True).encode()
    assert _cache_stem("p", n=3) == "p_" + hashlib.sha256(plain).hexdigest()[:12]
    assert _cache_stem("p", materials="by_kind", n=3) != _cache_stem("p", n=3)
    now = _cache_stem("p", n=3)
    monkeypatch.setattr(rooms, "ROOMS_VERSION", 1)  # the rooms without beds, before session 71
    assert _cache_stem("p", n=3) != now
    monkeypatch.undo()
    kw = dict(num_scenes=2, grid="icosahedral:2", progress=False,
              camera=cameras.Equirectangular(32, 16))
    rand = RoomsSegmentation(tmp_path, "test", **kw)
    kind = RoomsSegmentation(tmp_path, "test", materials="by_kind", **kw)
    assert rand.processed_paths != kind.processed_paths
    assert torch.equal(rand.y, kind.y) and not torch.equal(rand.x, kind.x)  # same rooms, new looks
    direct = scenes.render(scenes.make_room(kind.scene_seed, 1, materials="by_kind"), kw["camera"],
                           *view_pose(scenes.make_room(kind.scene_seed, 1), "none", 1, kind.scene_seed))
    assert np.array_equal(kind.image[1].numpy(), direct.rgb)
    up = RoomsGravity(tmp_path, 2, camera=kw["camera"], grid="icosahedral:2", progress=False,
                      materials="by_kind")
    assert not torch.equal(up.x, RoomsGravity(tmp_path, 2, camera=kw["camera"], grid="icosahedral:2",
                                              progress=False).x)
    with pytest.raises(ValueError, match="materials must be one of"):
        RoomsDetection(tmp_path, "test", materials="paint", **kw)


def test_worker_processes_load_the_same_batches(tmp_path):
    """PyG's DataLoader with worker processes (the dataset pickled into each) gives the
    batches loaded here, every field equal."""
    ds = RoomsSegmentation(tmp_path, "train", camera=cameras.Equirectangular(64, 32),
                           grid="icosahedral:3", num_scenes=4, progress=False)
    here = list(DataLoader(ds, batch_size=2))
    there = list(DataLoader(ds, batch_size=2, num_workers=2))
    assert len(here) == len(there) == 2
    for a, b in zip(here, there):
        assert a.keys() == b.keys()
        for key in a.keys():
            assert torch.equal(a[key], b[key]), key
