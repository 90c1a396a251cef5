"""Nerfstudio's and Instant-NGP's transforms.json, checked against pycolmap: nerfstudio
copies COLMAP's parameters, principal point and pixel convention included."""

import json
import math

import numpy as np
import pycolmap
import pytest

from tests.helpers import FIXTURES
from usf_graph import cameras as C
from usf_graph.cameras.colmap import HALF_PIXEL
from usf_graph.cli import main

W, H = 640, 480
FIXTURE = FIXTURES / "nerfstudio_transforms.json"  # as ns-process-data writes it
_FISHEYE = json.loads(FIXTURE.read_text())
# (transforms.json fields, the COLMAP model and parameters they hold)
CASES = {
    "opencv": ({"camera_model": "OPENCV", "fl_x": 520.3, "fl_y": 518.9, "cx": 321.7, "cy": 238.4,
                "k1": -0.21, "k2": 0.05, "p1": 0.0012, "p2": -0.0008},
               "OPENCV", [520.3, 518.9, 321.7, 238.4, -0.21, 0.05, 0.0012, -0.0008]),
    "opencv_k3": ({"camera_model": "OPENCV", "fl_x": 410.0, "fl_y": 412.5, "cx": 318.2, "cy": 243.9,
                   "k1": -0.12, "k2": 0.03, "k3": -0.004, "p1": 0.0005, "p2": 0.0002},
                  "FULL_OPENCV", [410.0, 412.5, 318.2, 243.9, -0.12, 0.03, 0.0005, 0.0002, -0.004, 0, 0, 0]),
    "pinhole": ({"camera_model": "PINHOLE", "fl_x": 600.0, "fl_y": 600.0, "cx": 320.0, "cy": 240.0},
                "PINHOLE", [600.0, 600.0, 320.0, 240.0]),
    "instant_ngp": ({"camera_angle_x": 1.2}, "PINHOLE",  # no model, no centre: a pinhole, centred
                    [0.5 * W / math.tan(0.6)] * 2 + [W / 2, H / 2]),
    "instant_ngp_narrow": ({"camera_angle_x": 0.9, "camera_angle_y": 0.7}, "PINHOLE",  # under a radian
                           [0.5 * W / math.tan(0.45), 0.5 * H / math.tan(0.35), W / 2, H / 2]),
    "fisheye": ({k: _FISHEYE[k] for k in ("camera_model", "fl_x", "fl_y", "cx", "cy", "k1", "k2", "k3", "k4")},
                "OPENCV_FISHEYE", [_FISHEYE[k] for k in ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "k3", "k4")]),
}


def write(path, fields, frames=None):
    frames = frames if frames is not None else [{"file_path": "images/a.jpg", "transform_matrix": np.eye(4).tolist()}]
    path.write_text(json.dumps({"w": W, "h": H, **fields, "frames": frames}))
    return path


@pytest.mark.parametrize("case", sorted(CASES))
def test_transforms_cameras_project_as_pycolmap_reads_their_parameters(tmp_path, case):
    fields, model, params = CASES[case]
    cam = C.load(write(tmp_path / "transforms.json", fields))
    assert type(cam) is (C.KannalaBrandt if "FISHEYE" in model else C.Pinhole)
    ref = pycolmap.Camera.create_from_model_name(1, model, 1.0, W, H)
    ref.params = params
    rays = np.random.default_rng(0).normal(size=(4000, 3)) + [0, 0, 2.0]  # COLMAP's frame: z ahead
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    rays = rays[rays[:, 2] > 0.5]  # within 60 degrees: short of where the distortions fold
    theirs = np.asarray(ref.img_from_cam(rays), np.float64)
    ours, seen = cam.sees(rays @ C.DEFAULT_ROTATION.T)
    inside = np.all((theirs >= 0) & (theirs <= [W, H]), -1)
    assert inside.sum() > 1000 and seen[inside].all()
    np.testing.assert_allclose(ours[inside] + HALF_PIXEL, theirs[inside], atol=1e-6, rtol=0)


def test_the_fixture_reads_from_the_command_line_as_a_fisheye(capsys):
    assert main(["camera", str(FIXTURE)]) == 0
    out = capsys.readouterr().out
    assert "KannalaBrandt" in out and "876 x 584" in out
    assert main(["camera", str(FIXTURE), "--key", "images/DSC00001.JPG"]) == 2
    assert "every frame has the file's camera; leave the key out" in capsys.readouterr().err
    assert [(k, c.key()) for k, c in C.load_all(FIXTURE).items()] == [(None, C.load(FIXTURE).key())]


def test_frames_with_their_own_intrinsics_are_picked_by_file_path(tmp_path):
    top = {"camera_model": "OPENCV", "fl_x": 500.0, "cx": 320.0, "cy": 240.0}
    frames = [{"file_path": "./images/a.jpg", "fl_x": 500.0, "fl_y": 500.0},
              {"file_path": "./images/b.jpg", "fl_x": 450.0, "fl_y": 455.0, "k1": -0.1}]
    path = write(tmp_path / "transforms.json", top, frames)
    with pytest.raises(ValueError, match=r"cameras of their own \(intrinsics or masks; 2 frames, "
                                         r"e.g. './images/a.jpg'\); choose one by its file_path"):
        C.load(path)
    b = C.load(path, key="images/b.jpg")  # with or without ./
    assert (b.fx, b.fy, b.cx, b.cy) == (450.0, 455.0, 320.0 - HALF_PIXEL, 240.0 - HALF_PIXEL)
    assert b.dist[0] == -0.1 and C.load(path, key="./images/a.jpg").fy == 500.0
    assert sorted(C.load_all(path)) == ["./images/a.jpg", "./images/b.jpg"]
    with pytest.raises(ValueError, match=r"no frame with file_path 'c.jpg' \(e.g. './images/a.jpg'\)"):
        C.load(path, key="c.jpg")
    # frames without intrinsics, at the top or in a frame: not a transforms.json
    (tmp_path / "poses.json").write_text(json.dumps({"frames": [{"file_path": "a.jpg", "w": W}]}))
    with pytest.raises(ValueError, match=r"unrecognized calibration format \(top-level keys: \['frames'\]\)"):
        C.load(tmp_path / "poses.json")


def test_bad_transforms_get_errors_that_name_the_fix(tmp_path):
    good = {"camera_model": "OPENCV", "fl_x": 500.0, "fl_y": 500.0, "cx": 320.0, "cy": 240.0}
    for fields, why in (({**good, "k4": 0.01}, "k4=0.01: the r\\^8 term"),
                        ({**good, "camera_model": "VR180_L"}, "camera_model 'VR180_L' is not read here"),
                        ({**good, "camera_model": "OPENCV_FISHEYE", "p1": 0.1}, "no tangential terms"),
                        ({"camera_model": "OPENCV"}, "give fl_x \\(pixels\\) or camera_angle_x"),
                        ({"camera_angle_x": 3.5}, "between 0 and pi"),
                        ({"camera_angle_x": 0.0}, "between 0 and pi radians, got 0.0"),
                        ({**good, "fl_x": float("nan")}, "'fl_x' must be finite")):
        with pytest.raises(ValueError, match=why):
            C.load(write(tmp_path / "transforms.json", fields))
    path = tmp_path / "no_size.json"
    path.write_text(json.dumps({**good, "frames": []}))
    with pytest.raises(ValueError, match="missing key 'w'.*as w and h"):
        C.load(path)
    pano = C.load(write(tmp_path / "pano.json", {"camera_model": "EQUIRECTANGULAR"}))
    assert type(pano) is C.Equirectangular and (pano.width, pano.height) == (W, H)


def test_an_images_own_frame_picks_its_camera(tmp_path):
    """Without a key, each image takes its transforms.json frame's camera: ``frame_key``,
    ``render``, and ``predict`` on two frames of two cameras at once, each frame's labels
    those of a run with its ``--key``."""
    import cv2

    from tests.helpers import tiny_seg_checkpoint

    top = {"camera_model": "OPENCV", "cx": 32.0, "cy": 24.0}
    frames = [{"file_path": "./images/a.png", "fl_x": 40.0, "fl_y": 40.0},
              {"file_path": "images/b.png", "fl_x": 25.0, "fl_y": 25.0, "k1": -0.05}]
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps({"w": 64, "h": 48, **top, "frames": frames}))
    (tmp_path / "images").mkdir()
    rng = np.random.default_rng(0)
    for name in ("a", "b"):
        cv2.imwrite(str(tmp_path / "images" / f"{name}.png"),
                    cv2.GaussianBlur(rng.integers(0, 256, (48, 64, 3)).astype(np.uint8), (7, 7), 2))
    a, b = (str(tmp_path / "images" / f"{n}.png") for n in "ab")
    assert C.frame_key(path, b) == "images/b.png" and C.frame_key(path, a) == "./images/a.png"
    assert C.frame_key(path, tmp_path / "other.png") is None and C.frame_key(FIXTURE, a) is None
    outs = {}
    for name, argv in (("auto", [b]), ("key", [b, "--key", "images/b.png"]), ("other", [b, "--key", "./images/a.png"])):
        assert main(["render", *argv, "--camera", str(path), "--to", "equirectangular:64x32",
                     "--out", str(tmp_path / f"{name}.png")]) == 0
        outs[name] = cv2.imread(str(tmp_path / f"{name}.png"))
    assert np.array_equal(outs["auto"], outs["key"]) and not np.array_equal(outs["auto"], outs["other"])
    tiny_seg_checkpoint(tmp_path / "seg.pt", size=32)
    labels = {}
    for name, argv in (("both", [a, b]), ("a", [a, "--key", "./images/a.png"]), ("b", [b, "--key", "images/b.png"])):
        assert main(["predict", "seg", str(tmp_path / "seg.pt"), *argv, "--camera", str(path),
                     "--up", "0", "0", "1", "--out", str(tmp_path / name)]) == 0
        labels.update({(name, p.name): cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
                       for p in (tmp_path / name).glob("*labels.png")})
    assert len(labels) == 4
    for n in "ab":
        assert np.array_equal(labels[("both", f"{n}_labels.png")], labels[(n, f"{n}_labels.png")]), n


def test_a_frames_mask_is_its_cameras_image_mask(tmp_path):
    """nerfstudio's per-frame ``mask_path`` (zero: ignored), from the file's folder: the
    frame's camera ignores those pixels; a mask of another size is refused."""
    import cv2

    mask = np.full((H, W), 255, np.uint8)
    mask[:100, :200] = 0
    (tmp_path / "masks").mkdir()
    cv2.imwrite(str(tmp_path / "masks" / "a.png"), mask)
    frames = [{"file_path": "images/a.jpg", "mask_path": "masks/a.png"}, {"file_path": "images/b.jpg"}]
    path = write(tmp_path / "transforms.json", CASES["fisheye"][0], frames)
    a, b = C.load(path, key="images/a.jpg"), C.load(path, key="images/b.jpg")
    assert np.array_equal(a.image_mask, mask > 0) and b.image_mask is None
    assert a.lens_normal_map()[1][:100, :200].sum() == 0 and b.lens_normal_map()[1][:100, :200].any()
    assert C.frame_key(path, tmp_path / "images" / "a.jpg") == "images/a.jpg"
    cv2.imwrite(str(tmp_path / "masks" / "a.png"), mask[:50])
    with pytest.raises(ValueError, match=r"transforms.json \[images/a.jpg\]: mask_path 'masks/a.png': image mask has shape \(50, 640\)"):
        C.load(path, key="images/a.jpg")
