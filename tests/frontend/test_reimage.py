"""Reimager: one camera's images seen through another, the geometry built once; its
cv2.remap fast path against the exact table and against scipy's bilinear sampling."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from tests.helpers import FIXTURES
from usf_graph import cameras
from usf_graph.frontend import Reimager, RigReimager, blend_weights, render, render_rig
from usf_graph.frontend.remap import Remap
from usf_graph.geometry import rotation_from_axis_angle


def pairs(seed):
    """Source and target cameras that change with ``seed``: a fisheye with a random image
    mask (pixels without a ray past its circle too), a distorted pinhole, a turned
    panorama (it wraps in u)."""
    rng = np.random.default_rng(seed)
    mask = rng.random((48, 64)) > 0.15
    fish = cameras.KannalaBrandt(18.0 + rng.random(), 18.0, 31.5, 23.5, 64, 48,
                                 k=(0.01, -0.002, 0.0, 0.0)).with_fov(190).with_image_mask(mask)
    pin = cameras.Pinhole(40.0, 41.0, 29.5 + rng.random(), 19.5, 60, 40, dist=(-0.2, 0.05, 0.001, 0.0, 0.0))
    axis = rng.normal(size=3)
    turn = rotation_from_axis_angle(axis / np.linalg.norm(axis), rng.uniform(0.2, 1.0))
    pano = cameras.Equirectangular(96, 48).with_rotation(turn)
    return [(fish, pano), (pano, fish), (pin, pano), (pano, pin), (fish, pin)]


def scipy_reference(image, cam_src, cam_dst):
    """Each target pixel's ray projected into the source and sampled there by
    ``scipy.ndimage.map_coordinates`` (bilinear), and the pixels whose four neighbours are
    all readable: where the library must agree with it."""
    rays, valid = cam_dst.lens_normal_map()
    uv, seen = cam_src.sees(np.where(valid[..., None], rays, 1.0))
    seen &= valid
    u, v = np.nan_to_num(uv[..., 0]), np.nan_to_num(uv[..., 1])
    v = np.clip(v, 0, cam_src.height - 1)
    u = np.mod(u, cam_src.width) if cam_src.wraps_u else np.clip(u, 0, cam_src.width - 1)
    mode = "grid-wrap" if cam_src.wraps_u else "nearest"
    out = np.stack([ndimage.map_coordinates(image[..., c], [v, u], order=1, mode=mode)
                    for c in range(image.shape[-1])], -1)
    ok = cam_src.unproject(cam_src.pixel_grid())[1]
    if cam_src.image_mask is not None:
        ok &= cam_src.image_mask
    i0, j0 = np.floor(v).astype(int), np.floor(u).astype(int)
    i1 = np.minimum(i0 + 1, cam_src.height - 1)
    j1 = (j0 + 1) % cam_src.width if cam_src.wraps_u else np.minimum(j0 + 1, cam_src.width - 1)
    clean = seen & ok[i0, j0] & ok[i0, j1] & ok[i1, j0] & ok[i1, j1]
    return np.where(seen[..., None], out, 0.0), clean


@settings(max_examples=6, deadline=None)
@given(st.integers(0, 10_000))
def test_fast_path_and_exact_table_agree_with_scipy_on_new_cameras_and_masks(seed):
    """On cameras and masks that change between calls: the float64 table equals scipy's
    bilinear sampling wherever every neighbour is readable, the float32 ``cv2.remap`` path
    is within OpenCV's 1/32 pixel of it everywhere, both see the same pixels, and whatever
    the unreadable pixels hold (NaN) never shows."""
    rng = np.random.default_rng(seed)
    for src, dst in pairs(seed):
        img = rng.random((src.height, src.width, 3))
        valid = src.unproject(src.pixel_grid())[1]
        if src.image_mask is not None:
            valid &= src.image_mask
        img[~valid] = np.nan
        r = Reimager(src, dst)
        exact, fast = r(img), r(img.astype(np.float32))
        assert exact.dtype == np.float64 and fast.dtype == np.float32
        ref, clean = scipy_reference(np.nan_to_num(img), src, dst)
        assert clean.sum() > 0.5 * r.seen.sum() > 0
        np.testing.assert_allclose(exact[clean], ref[clean], rtol=0, atol=1e-12)
        assert np.isfinite(exact).all() and np.isfinite(fast).all()
        assert np.array_equal(exact.any(-1) | r.seen, r.seen)  # nothing outside what it sees
        assert (fast[~r.seen] == 0).all() and np.abs(fast - exact).max() < 1 / 32
        assert np.abs(fast - exact).max() > 0  # not the table under another name
        # the pixels next to unreadable ones blend the readable ones, exactly as the table
        np.testing.assert_allclose(fast[r.seen & ~clean], exact[r.seen & ~clean], atol=1 / 32)
        # a share of the pixels (a rig's camera's) as if built for them alone
        keep = rng.random(r.seen.size) < 0.5
        part = r.part(keep)
        alone = Remap(src, r._uv, r._sees & keep, "bilinear", r._valid)
        assert np.array_equal(part.reached, alone.reached) and part.reached.sum() > 0
        a32 = img.astype(np.float32)
        np.testing.assert_array_equal(part(a32), alone(a32))


def test_one_reimager_serves_many_images_of_every_type():
    """Built once, it re-images each new image as :func:`render` does; integer images keep
    their type within a grey level of the exact result, torch stays torch (with
    gradients: each source pixel's weight summed over the target), and nearest copies
    labels."""
    fish, pano = pairs(3)[0]
    r = Reimager(fish, pano)
    rng = np.random.default_rng(1)
    for _ in range(3):
        img = (rng.random((48, 64, 3)) * 255).astype(np.uint8)
        out = r(img)
        assert out.dtype == np.uint8 and np.array_equal(out, render(img, fish, pano))
        exact = r(img.astype(np.float64)).round()
        assert np.abs(out - exact).max() <= 1 and (out != exact).mean() < 0.2
    deep = r((rng.random((48, 64)) * 65535).astype(np.uint16))
    assert deep.dtype == np.uint16 and deep.shape == (48, 96)
    t = torch.rand(48, 64, 2, dtype=torch.float64, requires_grad=True)
    out = r(t)
    assert isinstance(out, torch.Tensor) and out.shape == (48, 96, 2)
    out[..., 0].sum().backward()
    idx, w = r._entries()
    np.testing.assert_allclose(t.grad[..., 0].numpy().ravel(),
                               np.bincount(idx.ravel(), w.ravel(), minlength=48 * 64), atol=1e-12)
    assert (t.grad[..., 1] == 0).all()
    labels = rng.integers(0, 13, (48, 64)).astype(np.uint8)
    near = Reimager(fish, pano, "nearest")
    got = near(labels)
    assert set(np.unique(got[near.seen])) <= set(np.unique(labels[fish.image_mask]))
    assert (got == near(labels.astype(np.int64))).mean() > 0.995  # cv2's rounding at half pixels
    # a bool mask as torch (the exact table's path) stays a bool mask, read where seen
    hidden = torch.as_tensor(labels > 6)
    moved = near(hidden)
    assert moved.dtype == torch.bool and moved.shape == (48, 96)
    assert torch.equal(moved, torch.as_tensor(near((labels > 6).astype(np.uint8)) == 1))


def test_reimager_refuses_what_it_cannot_use():
    fish, pano = pairs(0)[0]
    r = Reimager(fish, pano)
    with pytest.raises(ValueError, match="the camera expects"):
        r(np.zeros((40, 64, 3), np.uint8))
    with pytest.raises(ValueError, match="interpolation must be one of"):
        Reimager(fish, pano, "area")
    with pytest.raises(ValueError, match="the camera's image"):
        Reimager(fish, pano, source_valid=np.ones((10, 10), bool))
    assert "Reimager(" in repr(r) and "seen=" in repr(r)


def test_rig_reimager_serves_many_frames_as_render_rig():
    """A rig's stitching built once gives each frame what :func:`render_rig` gives it, and
    what each camera's exact re-imaging blended by :func:`blend_weights` gives (each camera
    samples only its share of the pixels)."""
    rig = {n: c.with_fov(190) for n, c in cameras.load_rig(FIXTURES / "kalibr_rig.yaml").items()}
    pano = cameras.Equirectangular(96, 48)
    rr = RigReimager(rig, pano, blend="feather")
    assert rr.seen.all()  # two 190-degree fisheyes back to back
    rng = np.random.default_rng(2)
    for _ in range(2):
        frames = [(rng.random((c.height, c.width, 3)) * 255).astype(np.uint8) for c in rig.values()]
        out = rr(frames)
        assert out.dtype == np.uint8 and out.shape == (48, 96, 3)
        assert np.array_equal(out, render_rig(frames, rig, pano, blend="feather"))
        assert np.array_equal(out, rr(dict(reversed(list(zip(rig, frames))))))
    rays, valid = pano.lens_normal_map()
    floats = [rng.random((c.height, c.width, 2)) for c in rig.values()]
    for blend in ("best", "feather"):
        alone = [Reimager(c, pano) for c in rig.values()]
        w, _ = blend_weights(list(rig.values()), np.where(valid[..., None], rays, 1.0).reshape(-1, 3),
                             np.stack([r.seen.ravel() for r in alone]), blend)
        want = sum(wk.reshape(48, 96, 1) * r(f) for wk, r, f in zip(w, alone, floats))  # float64: exact
        got = RigReimager(rig, pano, blend=blend)([f.astype(np.float32) for f in floats])
        assert got.dtype == np.float32 and 0 < np.abs(got - want).max() < 1 / 32
