"""A trained model on one image of any camera (``train.apply``, what ``usf-graph predict``
runs), checked against a lift written here from the frontend's float64 table, the
protocols' own datasets and predictions, and with bad inputs."""

import inspect
import warnings

import cv2
import numpy as np
import pytest
import torch

from usf_graph.cameras import Equirectangular, KannalaBrandt, Pinhole
from usf_graph.frontend import SphericalFrontend
from usf_graph.geometry import random_rotation
from usf_graph.grids import icosahedral
from usf_graph.models import PlanarUNet, SphericalDetector, SphericalUNet
from usf_graph.models.gravity import UNSURE_MARGIN
from usf_graph.ops import box_iou
from usf_graph.train.apply import (
    UNSEEN,
    choose_interpolation,
    class_names,
    detect_image,
    lift_for,
    rgb01,
    rgb_channels,
    segment_image,
)
from usf_graph.train.seg import protocol_sets
from usf_graph.train.seg_eval import predict


@pytest.fixture(scope="module")
def views(tmp_path_factory):
    return protocol_sets(tmp_path_factory.mktemp("rooms"), size=32, level=3, num_train=0,
                         num_test=2, tests=("a", "c"), progress=False)


def _segmenter():
    torch.manual_seed(0)
    net = SphericalUNet(13, level=3, channels=(8, 8, 8, 8), gravity=True).eval()
    with torch.no_grad():  # confident logits: an untrained head gives near-uniform ones
        net.head.weight.mul_(30)
    return net


def _reference_input(image: np.ndarray, camera, level: int = 3):
    """The image lifted by the frontend's sparse float64 table (not the cv2.remap path
    that lift takes for numpy images), RGB / 255."""
    fe = SphericalFrontend(camera, icosahedral(level))
    x = fe.lift_batch(torch.as_tensor(image[None]).double() / 255).float()
    return x, None if fe.mask.all() else fe.mask


@pytest.mark.parametrize("test", ["a", "c"])
def test_segment_image_reads_the_image_as_the_protocol_does(views, test):
    ds, net = views[test], _segmenter()
    pix, _ = predict(net, ds, progress=False)
    for i in range(len(ds)):
        img = ds.image[i].numpy()
        r = segment_image(net, img, ds.camera, interpolation="bilinear")
        x, mask = _reference_input(img, ds.camera)
        assert torch.allclose(x, ds.x[i:i + 1].float(), atol=1e-3)  # the stored split (float16)
        _, lifted, m = lift_for(net, img, ds.camera, "bilinear")
        assert torch.allclose(lifted, x, atol=1e-6) and (m is None) == (mask is None)
        assert (lift_for(net, img[..., ::-1], ds.camera, "bilinear")[1] - x).abs().max() > 0.1
        with torch.no_grad():
            want = net(x, mask).softmax(-1)[0]
        assert np.allclose(r["probs"], want.numpy(), atol=1e-5)
        # labels: the protocol's pixels where the camera sees, UNSEEN where it has no ray
        seen = ds.label_image[i].numpy() != 255
        assert ((r["labels"] == UNSEEN) == ~seen).all()
        assert (r["labels"][seen] == pix[i][seen]).mean() > 0.99
        assert (r["points"][~ds.mask[0].numpy()] == UNSEEN).all()
        assert r["source"] == "estimated" and r["unsure"] == (r["margin"] < UNSURE_MARGIN)
        assert r["interpolation"] == "bilinear"
    if test == "c":
        assert (r["labels"] == UNSEEN).any()  # the fisheye's corners


def test_a_given_up_is_read_instead_of_the_estimate(views):
    ds, net = views["a"], _segmenter()
    img = ds.image[0].numpy()
    up = torch.tensor([0.3, -0.2, 0.9])
    r = segment_image(net, img, ds.camera, up=2 * up.numpy(), interpolation="bilinear")
    x, _ = _reference_input(img, ds.camera)
    with torch.no_grad():
        want = net(x, up=(up / up.norm())[None]).softmax(-1)[0]
    assert np.allclose(r["probs"], want.numpy(), atol=1e-5)
    assert r["source"] == "given" and np.allclose(r["up"], (up / up.norm()).numpy())
    est = segment_image(net.train(), img, ds.camera, interpolation="bilinear")
    assert net.training  # evaluated in eval mode, its own mode given back
    assert np.allclose(est["probs"], segment_image(net.eval(), img, ds.camera,
                                                   interpolation="bilinear")["probs"])
    assert np.abs(est["probs"] - r["probs"]).max() > 1e-3
    for bad in ([0, 0, 0], [1, 2], [np.nan, 0, 1]):
        with pytest.raises(ValueError, match="up must be 3 finite numbers"):
            segment_image(net, img, ds.camera, up=bad)
    with pytest.raises(ValueError, match="gravity=True"):  # a model without an estimate
        segment_image(SphericalUNet(13, level=3, channels=(8, 8, 8, 8)), img, ds.camera, up=[0, 0, 1])


def _assert_same_boxes(a, b):
    """Boxes alike: centres and sizes to 1e-4 rad, and as regions (IoU). The roll of a
    near-square box is ill-conditioned (an untrained head's: lifts 2e-7 apart turned it
    4e-4, IoU 0.9997), so the reference lift's boxes are compared this loosely, and the
    boxes of detect_image's own lift (checked against the reference) to 1e-9."""
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape and np.allclose(a[:, :4], b[:, :4], atol=1e-4)
    assert box_iou(torch.as_tensor(a), torch.as_tensor(b)).min() > 0.99


def test_detect_image_equals_the_detector_on_the_reference_lift(views):
    ds = views["c"]
    torch.manual_seed(1)
    det = SphericalDetector(12, input_level=3, head_level=2, min_level=1, channels=(8, 8, 8),
                            gravity=True).eval()
    img = ds.image[0].numpy()
    r = detect_image(det, img, ds.camera, interpolation="bilinear", threshold=0.0, k=10)
    x, mask = _reference_input(img, ds.camera)
    _, lifted, m = lift_for(det, img, ds.camera, "bilinear")
    assert torch.allclose(lifted, x, atol=1e-6) and torch.equal(m, mask)
    with torch.no_grad():
        want = det.decode(det(x, mask), k=10, threshold=0.0)[0]
        own = det.decode(det(lifted, m), k=10, threshold=0.0)[0]
    assert len(r["boxes"]) == len(want["boxes"]) > 0
    _assert_same_boxes(r["boxes"], want["boxes"])
    np.testing.assert_allclose(r["boxes"], own["boxes"], rtol=0, atol=1e-9)
    assert np.array_equal(r["classes"], want["classes"])
    assert np.allclose(r["scores"], want["scores"], atol=1e-5)
    assert r["source"] == "estimated" and len(r["up"]) == 3
    u = torch.tensor([[0.6, 0.0, 0.8]])  # a given up reaches the detector
    given = detect_image(det, img, ds.camera, up=u[0].tolist(), interpolation="bilinear",
                         threshold=0.0, k=10)
    with torch.no_grad():
        want = det.decode(det(x, mask, up=u), k=10, threshold=0.0)[0]
    assert given["source"] == "given"
    _assert_same_boxes(given["boxes"], want["boxes"])
    assert len(given["scores"]) != len(r["scores"]) or not np.allclose(given["scores"], r["scores"], atol=1e-3)
    # its decoding defaults are the detector's
    ours = inspect.signature(detect_image).parameters
    for name, p in inspect.signature(det.decode_image).parameters.items():
        if name in ("threshold", "k", "nms", "drop_hidden"):
            assert ours[name].default == p.default, name


def test_bad_images_cameras_and_models_are_refused(views):
    ds, net = views["a"], _segmenter()
    img = ds.image[0].numpy()
    with pytest.raises(ValueError, match="planar"):
        segment_image(PlanarUNet(13, channels=(4, 4)), img, ds.camera)
    with pytest.raises(ValueError, match=r"RGB images \[H, W, 3\]"):
        segment_image(net, img[..., :2], ds.camera)
    with pytest.raises(ValueError, match="up must be 3 numbers, None .* or 'lines', got 'north'"):
        segment_image(net, img, ds.camera, up="north")
    gray = img.mean(-1).round().astype(np.uint8)  # a mono camera's image: read as R = G = B
    with pytest.warns(UserWarning, match="grayscale image is read as R = G = B"):
        mono = segment_image(net, gray, ds.camera)["probs"]
    assert np.array_equal(mono, segment_image(net, np.dstack([gray] * 3), ds.camera)["probs"])
    with pytest.warns(UserWarning, match="grayscale"):
        assert np.array_equal(segment_image(net, gray[..., None], ds.camera)["probs"], mono)
    with pytest.warns(UserWarning, match="grayscale"):  # read alone, it assumes a colour model too
        assert np.array_equal(rgb_channels(gray), np.dstack([gray] * 3))
    torch.manual_seed(0)  # a model for mono cameras takes it silently, and colour as its luma
    mono_net = SphericalUNet(13, level=3, channels=(8, 8, 8, 8), gravity=True, gray=True).eval()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        segment_image(mono_net, gray, ds.camera)
    luma = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)  # a mono camera's image of the same room
    np.testing.assert_allclose(segment_image(mono_net, img, ds.camera)["probs"],
                               segment_image(mono_net, luma, ds.camera)["probs"], rtol=0, atol=2e-3)
    with pytest.raises(ValueError, match=r"\[0, 1\].*divide by 255"):
        segment_image(net, img.astype(np.float32), ds.camera)
    with pytest.raises(ValueError, match="dtype int64"):
        segment_image(net, img.astype(np.int64), ds.camera)
    with pytest.raises(ValueError, match=r"camera.resized\(W, H\)"):
        segment_image(net, img[:, :-2], ds.camera)
    # a field of view of 0.001 degrees, looking between grid points
    blind = Pinhole(1e5, 1e5, 0.5, 0.5, 2, 2, rotation=random_rotation(seed=3).numpy())
    with pytest.raises(ValueError, match="empty field of view"):
        segment_image(net, np.zeros((2, 2, 3), np.uint8), blind, interpolation="bilinear")
    # the same picture as uint8, uint16 and float in [0, 1], and RGBA: one answer
    want = segment_image(net, img, ds.camera)["probs"]
    for same in (img.astype(np.uint16) * 257, img.astype(np.float32) / 255,
                 np.dstack([img, np.full(img.shape[:2], 7, np.uint8)])):
        assert np.allclose(segment_image(net, same, ds.camera)["probs"], want, atol=1e-5)
    assert rgb01(img).dtype == np.float32
    with pytest.warns(UserWarning, match="grayscale"):  # read for a colour model by default
        assert np.array_equal(rgb01(img[..., 0]), np.dstack([img[..., 0]] * 3) / np.float32(255))


def test_auto_interpolation_averages_where_the_image_is_finer_than_the_grid():
    grid = icosahedral(3)  # spacing about 7.6 degrees
    assert choose_interpolation(Equirectangular(64, 32), grid) == "bilinear"  # 4-5 degree pixels
    fish = KannalaBrandt(150.0, 150.0, 255.5, 255.5, 512, 512, k=(0.0, 0.0, 0.0, 0.0))
    assert choose_interpolation(fish, grid) == "area"  # 0.4 degree pixels
    assert choose_interpolation(Equirectangular(64, 32), icosahedral(6)) == "bilinear"


def test_class_names():
    assert class_names("seg", 13)[3] == "ceiling" and len(class_names("det", 12)) == 12
    assert len(class_names("det", 47)) == 47 and class_names("det", 5)[4] == "class 4"
    assert class_names("seg", 10)[1] == "road" and class_names("seg", 10)[9] == "traffic_sign"


def test_a_rig_is_one_sphere_and_answers_in_each_camera(views):
    """Two back-to-back fisheyes of a Kalibr camchain: lifted onto one sphere (checked
    against the rig's float64 table path), labels rendered back into each camera."""
    from tests.helpers import FIXTURES
    from usf_graph.cameras import load_rig
    from usf_graph.frontend import RigFrontend, render
    from usf_graph.viz import labelled_panorama

    rig = {n: c.with_fov(190) for n, c in load_rig(FIXTURES / "kalibr_rig.yaml").items()}
    pano = labelled_panorama(256, 128)
    images = [(255 * render(pano, Equirectangular(256, 128), c)).round().astype(np.uint8)
              for c in rig.values()]
    net = _segmenter()
    r = segment_image(net, images, rig, interpolation="bilinear")
    fe = RigFrontend(rig, icosahedral(3))
    x = fe.lift_batch([torch.as_tensor(im[None]).double() / 255 for im in images]).float()
    with torch.no_grad():
        want = net(x, None if fe.mask.all() else fe.mask).softmax(-1)[0]
    assert np.allclose(r["probs"], want.numpy(), atol=1e-5)
    assert isinstance(r["labels"], list) and len(r["labels"]) == 2
    points = torch.as_tensor(want.argmax(-1).to(torch.uint8))
    for lab, f, cam in zip(r["labels"], fe.frontends, rig.values()):
        valid = cam.lens_normal_map()[1]
        assert ((lab == UNSEEN) == ~valid).all()
        assert np.array_equal(lab[valid], f.to_image(points, mode="nearest").numpy()[valid])
    assert r["labels"][0].shape == (400, 400) and not np.array_equal(r["labels"][0], r["labels"][1])
    assert segment_image(net, images, rig)["interpolation"] == "area"  # 400-pixel fisheyes
    named = segment_image(net, dict(zip(rig, images)), rig, interpolation="bilinear")
    assert np.allclose(named["probs"], r["probs"])
    with pytest.raises(ValueError, match="2 cameras.*1 images"):
        segment_image(net, images[:1], rig)
    with pytest.raises(ValueError, match="with_fov_and_mask"):
        segment_image(net, images, rig, image_mask=np.ones((400, 400), bool))


def test_an_image_mask_is_left_out_and_unseen(views):
    ds, net = views["c"], _segmenter()
    img = ds.image[0].numpy()
    left = np.zeros(img.shape[:2], bool)
    left[:, :16] = True
    r = segment_image(net, img, ds.camera, image_mask=left, interpolation="bilinear")
    same = segment_image(net, img, ds.camera.with_image_mask(left), interpolation="bilinear")
    assert np.array_equal(r["labels"], same["labels"]) and np.allclose(r["probs"], same["probs"])
    assert (r["labels"][:, 16:] == UNSEEN).all() and (r["labels"][:, :16] != UNSEEN).any()
    whole = segment_image(net, img, ds.camera, interpolation="bilinear")  # not the masked frontend
    assert (whole["labels"][:, 16:] != UNSEEN).any()
    # a camera with a mask of its own (its robot's body) keeps ignoring those pixels too
    top = np.zeros(img.shape[:2], bool)
    top[:20] = True
    both = segment_image(net, img, ds.camera.with_image_mask(top), image_mask=left,
                         interpolation="bilinear")["labels"]
    assert (both[20:] == UNSEEN).all() and (both[:, 16:] == UNSEEN).all() and (both[:20, :16] != UNSEEN).any()


def test_a_rigs_up_lines_read_every_cameras_lines_together():
    """``up="lines"`` on a rig: the estimate picks among the axes of all its cameras' lines
    (in the rig's frame), the same whether the cameras sit apart and are stitched at a
    distance or share a centre: where lines point does not depend on where one stands."""
    from usf_graph.cameras import stitch_at
    from usf_graph.frontend.lines import line_normals, manhattan_axes, rig_line_normals
    from usf_graph.geometry import rotation_from_axis_angle
    from usf_graph.scenes import make_room, render

    base = Pinhole(64.0, 64.0, 63.5, 63.5, 128, 128)
    rig = {"front": base, "left": base.turned(rotation_from_axis_angle(np.array([0.0, 0.0, 1.0]), np.pi / 2))}
    scene = make_room(seed=3, index=3, materials="by_kind")
    pos, R = scene.viewpoint(0)
    images = [render(scene, c, pos, R, boxes=False).rgb for c in rig.values()]
    n, w = rig_line_normals(images, rig.values())
    one = [line_normals(im, c) for im, c in zip(images, rig.values())]
    assert np.array_equal(n, np.concatenate([a for a, _ in one])) and len(n) > 40
    apart = stitch_at({k: c.with_position(np.array([0.05 * i, 0.0, 0.0])) for i, (k, c) in
                       enumerate(rig.items())}, 2.0)
    assert np.array_equal(rig_line_normals(images, apart.values())[0], n)
    axes = manhattan_axes(n, w)
    assert np.degrees(np.arccos(np.abs(axes @ R[2]).max())) < 1.0  # the room's up among them
    torch.manual_seed(0)
    det = SphericalDetector(12, input_level=3, head_level=2, min_level=1, channels=(8, 8, 8),
                            gravity=True).eval()
    r = detect_image(det, images, rig, up="lines")
    assert r["source"] == "lines" and np.isclose(np.abs(axes @ np.array(r["up"])).max(), 1.0, atol=1e-6)
    named = detect_image(det, dict(zip(reversed(list(rig)), reversed(images))), rig, up="lines")
    assert np.allclose(named["up"], r["up"])  # images by name, in any order
    # the rig's line finder, built on the first frame, serves the next: another room's, tilted
    other_room = make_room(seed=3, index=4, materials="by_kind")
    p2, R2 = other_room.viewpoint(0)
    R2 = R2 @ rotation_from_axis_angle(np.array([1.0, 0.0, 0.0]), np.radians(15))
    other = [render(other_room, c, p2, R2, boxes=False).rgb for c in rig.values()]
    axes2 = manhattan_axes(*rig_line_normals(other, rig.values()))
    r2 = detect_image(det, other, rig, up="lines")
    assert np.isclose(np.abs(axes2 @ np.array(r2["up"])).max(), 1.0, atol=1e-6)
    assert np.degrees(np.arccos(np.abs(axes2 @ R2[2]).max())) < 1.0
    with pytest.raises(ValueError, match="1 images for 2 cameras"):
        rig_line_normals(images[:1], rig.values())
