"""WoodScape on fixtures in the released layout (PNGs, per-image calibration JSON, OmniDet's
split lists): each image lifts through its own camera into the vehicle frame, where its
colours and labels land on the directions they were made for; the errors name the fix."""

import json
import os

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from usf_graph import cameras
from usf_graph.datasets import WoodScape

W, H = 128, 96


def _calibration(axis_yaw_deg: float) -> dict:
    """A 190-degree-class radial polynomial at 128 x 96, looking along the horizon at
    ``axis_yaw_deg`` (0: forward), its image's right to the right of where it looks."""
    yaw = np.radians(axis_yaw_deg)
    axis = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    R = np.stack([right, np.cross(axis, right), axis], 1)
    return {"extrinsic": {"quaternion": Rotation.from_matrix(R).as_quat().tolist(),
                          "translation": [0.0, 0.0, 1.0]},
            "intrinsic": {"aspect_ratio": 1.0, "cx_offset": 0.3, "cy_offset": -0.2, "height": H,
                          "k1": 33.0, "k2": -2.4, "k3": 4.2, "k4": -0.65, "model": "radial_poly",
                          "poly_order": 4, "width": W}, "name": "X"}


def _write(root, name, calib):
    """The image's colour encodes each pixel's ray in the vehicle frame ((z + 1) / 2 in red,
    (x + 1) / 2 in green, (y + 1) / 2 in blue); its labels are road (1) below -15 degrees, vehicles (6) above,
    and 12 and 10 (past the classes: void) in a band 75-87 degrees off the axis."""
    (root / "calibration_data" / "calibration").mkdir(parents=True, exist_ok=True)
    (root / "calibration_data" / "calibration" / f"{name}.json").write_text(json.dumps(calib))
    cam = cameras.load(root / "calibration_data" / "calibration" / f"{name}.json")
    rays, ok = cam.lens_normal_map()
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[..., 0] = np.round((rays[..., 2] + 1) / 2 * 255)
    rgb[..., 1] = np.round((rays[..., 0] + 1) / 2 * 255)
    rgb[..., 2] = np.round((rays[..., 1] + 1) / 2 * 255)
    label = np.where(rays[..., 2] < -np.sin(np.radians(15)), 1, 6).astype(np.uint8)
    off_axis = rays @ rays[H // 2, W // 2]  # the cosine of the angle to (about) its axis
    band = (off_axis > 0.05) & (off_axis < 0.25)  # outside the test's "inner" points
    label[band] = np.where(np.arange(W) < W // 2, 12, 10)[None].repeat(H, 0)[band]
    for folder, img in (("rgb_images", rgb[..., ::-1]), ("semantic_annotations/gtLabels", label)):
        (root / folder).mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / folder / f"{name}.png"), img)
    return rays, ok


@pytest.fixture
def release(tmp_path):
    root = tmp_path / "woodscape"
    _write(root, "00001_FV", _calibration(0))
    _write(root, "00002_RV", _calibration(180))
    _write(root, "00003_MVL", _calibration(90))
    (root / "train.txt").write_text("00001_FV.png\n00002_RV.png\n")
    (root / "val.txt").write_text("00003_MVL.png\n")
    return root


@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_each_image_lifts_through_its_own_camera_into_the_vehicle_frame(release, scale):
    ds = WoodScape(release, "train", grid="icosahedral:3", scale=scale, progress=False)
    assert len(ds) == 2 and ds.names == ["00001_FV", "00002_RV"]
    assert ds.camera_names == ["FV", "RV"]
    pos = ds.grid.pos.float()
    for i, forward in ((0, 1.0), (1, -1.0)):
        d = ds[i]
        seen = d.mask
        assert d.camera == ds.camera_names[i]
        # a camera sees what it faces: everything within 60 degrees of its axis, nothing
        # past its image's corners (115 degrees) by more than a grid spacing
        beyond = np.cos(np.radians(115) + ds.grid.spacing)
        assert seen[pos[:, 0] * forward > 0.5].all() and not seen[pos[:, 0] * forward < beyond].any()
        inner = seen & (pos[:, 0] * forward > 0.3)  # away from the image's border
        np.testing.assert_allclose(d.x[inner, 0], (pos[inner, 2] + 1) / 2, atol=0.03)
        np.testing.assert_allclose(d.x[inner, 1], (pos[inner, 0] + 1) / 2, atol=0.03)
        assert (d.x[~seen] == 0).all() and (d.y[~seen] == 255).all()
        low, high = inner & (pos[:, 2] < -0.4), inner & (pos[:, 2] > -0.1)
        assert low.sum() > 10 and high.sum() > 10
        assert (d.y[low] == 1).all() and (d.y[high] == 6).all()
        assert set(d.y[seen].tolist()) == {0, 1, 6}  # 10 and 12 are past the classes: void
    assert not torch.equal(ds.mask[0], ds.mask[1])
    assert torch.equal(ds.gravity[0], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    val = WoodScape(release, "val", grid="icosahedral:3", scale=scale, progress=False)
    assert val.names == ["00003_MVL"] and len(WoodScape(release, "all", grid="icosahedral:3",
                                                        scale=scale, progress=False)) == 3


def test_the_processed_split_is_reused_and_a_corrupt_one_rebuilt(release):
    first = WoodScape(release, "val", grid="icosahedral:2", progress=False)
    assert (first.frontend(0).camera.width, first.frontend(0).camera.height) == (W // 2, H // 2)
    path = next((release / "processed").glob("woodscape_val_*.pt"))
    stamp = os.stat(path).st_mtime_ns
    again = WoodScape(release, "val", grid="icosahedral:2", progress=False)
    assert os.stat(path).st_mtime_ns == stamp and len(again) == 1
    path.write_bytes(b"not a torch file")
    with pytest.warns(UserWarning, match="unreadable"):
        rebuilt = WoodScape(release, "val", grid="icosahedral:2", progress=False)
    assert torch.equal(rebuilt.x, again.x)


def test_missing_and_broken_data_name_the_fix(tmp_path, release):
    with pytest.raises(FileNotFoundError, match=r"^rgb_images, semantic_annotations not found under .*woodscape.valeo.com"):
        WoodScape(tmp_path / "nothing", "all", grid="icosahedral:2", progress=False)
    (release / "train.txt").unlink()
    with pytest.raises(FileNotFoundError, match="train.txt not found.*OmniDet"):
        WoodScape(release, "train", grid="icosahedral:2", progress=False)
    labels = release / "semantic_annotations" / "gtLabels" / "00003_MVL.png"
    cv2.imwrite(str(labels), np.zeros((H // 2, W // 2), np.uint8))
    with pytest.raises(ValueError, match=r"^00003_MVL: its calibration is 128x96, its label image "
                                         r"is 64x48, the image is 128x96; they must match"):
        WoodScape(release, "val", grid="icosahedral:2", progress=False)
    (release / "rgb_images" / "00003_MVL.png").write_bytes(b"\x89PNG broken")
    with pytest.raises(ValueError, match="00003_MVL.png is not a readable PNG"):
        WoodScape(release, "val", grid="icosahedral:2", progress=False)
    (release / "calibration_data" / "calibration" / "00003_MVL.json").unlink()
    with pytest.raises(FileNotFoundError, match="no calibration for 00003_MVL"):
        WoodScape(release, "val", grid="icosahedral:2", progress=False)
    with pytest.raises(ValueError, match="split must be"):
        WoodScape(release, "test", progress=False)
    for scale in (0, -0.5, 1.5):
        with pytest.raises(ValueError, match=r"scale must be in \(0, 1\]"):
            WoodScape(release, "val", grid="icosahedral:2", scale=scale, progress=False)
