"""A segmenter or detector bound to one camera and exported (ONNX, torch.export): the
written program gives usf-graph's labels or boxes on rendered rooms, says so in its
outputs where up is unusable, and every refusal names the fix."""

import json
import math
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from usf_graph.cameras import KannalaBrandt, Pinhole
from usf_graph.frontend import SphericalFrontend
from usf_graph.geometry import from_latlon
from usf_graph.grids import icosahedral
from usf_graph.models import SphericalDeepLabV3, SphericalDetector, SphericalUNet
from usf_graph.ops import box_iou
from usf_graph.scenes import make_room
from usf_graph.scenes.render import render
from usf_graph.train.apply import UNSEEN, detect_image, lift_for, segment_image
from usf_graph.train.bound import BoundDetector, BoundSegmenter, CameraIO
from usf_graph.train.export import (
    _angle,
    _load_pt2,
    _matched,
    _same_labels,
    export_model,
    load_exported,
)

pytest.importorskip("onnxruntime")
pytest.importorskip("onnxscript")


def _deeplab(seed=0, **kw):
    """A small DeepLab whose labels vary over a room (at initialization one class wins
    everywhere): its norms' statistics and its head centred on a rendered room's features."""
    torch.manual_seed(seed)
    cfg = dict(num_classes=5, level=3, channels=(4, 6), aspp_channels=8, rates=(2,),
               low_channels=4, pairs=0, gravity=True, upright=True, up_fields=2, upright_convs=2)
    model = SphericalDeepLabV3(**{**cfg, **kw})
    cam, up = _fisheye(32), torch.tensor([[0.0, 0.0, 1.0]])
    lifted = [lift_for(model, _room_image(cam, s), cam)[1:] for s in (7, 8)]
    with torch.no_grad():
        model.train()
        for x, mask in lifted:  # the norms' running statistics from rooms
            model(x, mask, up=up)
        seen = []
        hook = model.head.register_forward_hook(lambda m, i, o: seen.append(i[0][0]))
        model.eval()(*lifted[0], up=up)
        hook.remove()
        mean = seen[0][lifted[0][1]].mean(0)
        model.head.weight.mul_(500.0)
        model.head.bias.copy_(-model.head.weight @ mean)
    return model.eval()


def _fisheye(size=48):
    f = (size / 2) / math.radians(95)
    c = (size - 1) / 2
    return KannalaBrandt(f, f, c, c, size, size, k=(0.0, 0.0, 0.0, 0.0)).with_fov(190)


def _pinhole(w=40, h=30):
    return Pinhole(w / 2, w / 2, (w - 1) / 2, (h - 1) / 2, w, h)


def _room_image(camera, seed):
    return render(make_room(seed), camera, boxes=False).rgb


def test_onnx_with_an_imu_up_gives_usf_graphs_labels(tmp_path):
    model, cam = _deeplab(), _fisheye()
    path = tmp_path / "deploy" / "cam0" / "seg.onnx"  # its folders made
    info = export_model(model, cam, path, up="input")
    assert info["format"] == "ONNX" and info["check"]["agree"] >= 0.99
    assert info["path"] == str(path) and info["bytes"] == path.stat().st_size
    assert not list(path.parent.glob(".*part*"))  # written atomically
    run = load_exported(path)
    meta = run.metadata  # the file says what it is
    assert json.loads(meta["classes"]) == [f"class {k}" for k in range(5)] and meta["unseen"] == "255"
    assert meta["up"] == "input" and json.loads(meta["inputs"]) == ["image", "up"]
    assert json.loads(meta["cameras"])["image"] == cam.key() and meta["grid"] == "icosahedral:3"
    assert json.loads(meta["provenance"])["usf_graph"] == meta["usf_graph"]  # who wrote it
    for seed, up in ((1, [0.0, 0.0, 1.0]), (2, [0.3, -0.2, 0.9])):  # new rooms, a tilted up
        image = _room_image(cam, seed)
        labels, u = run(image, up)
        ref = segment_image(model, image, cam, up=up)
        seen = ref["labels"] != UNSEEN
        assert labels.dtype == np.uint8 and labels.shape == image.shape[:2]
        assert np.array_equal(labels == UNSEEN, ~seen)
        assert (labels[seen] == ref["labels"][seen]).mean() > 0.99
        assert len(np.unique(ref["labels"][seen])) > 1  # a test that a mirror would fail
        assert np.allclose(u, np.asarray(up) / np.linalg.norm(up), atol=1e-6)
    for bad in ([math.nan, 0.0, 1.0], [0.0, 0.0, 0.0]):  # no raising in a program: all unseen
        labels, u = run(image, bad)
        assert (labels == UNSEEN).all() and np.isnan(u).all()
    with pytest.raises(ValueError, match="takes 1 image and up; got 1 image$"):
        run(image)
    with pytest.raises(ValueError, match=r"shape \(48, 47, 3\); .* takes uint8 \[48, 48, 3\].*export it again"):
        run(image[:, :47], [0.0, 0.0, 1.0])


@pytest.mark.slow  # ONNX's export of the estimate's unrolled Jacobi rotations: about a minute
def test_onnx_holds_the_models_own_up_estimate(tmp_path):
    """ONNX has no eigendecomposition: the polish's Jacobi rotations stand in for it."""
    model, cam = _deeplab(1), _pinhole()
    with torch.no_grad():  # an untrained head's scores tie: sharpen them
        model.gravity.head.score.weight.mul_(3000.0)
    info = export_model(model, cam, tmp_path / "seg.onnx", up=None)
    assert info["inputs"] == ["image uint8 [30, 40, 3] RGB"] and info["check"]["agree"] >= 0.99
    run = load_exported(tmp_path / "seg.onnx")
    assert run.metadata["up"] == "estimate"
    sure = 0
    for seed in (0, 3, 6, 9):
        image = _room_image(cam, seed)
        labels, u = run(image)
        ref = segment_image(model, image, cam)
        if ref["margin"] < 1e-3:  # tied candidates (an untrained head): either may win
            continue
        sure += 1
        seen = ref["labels"] != UNSEEN
        assert (labels[seen] == ref["labels"][seen]).mean() > 0.99
        u, r = np.asarray(u, np.float64), np.asarray(ref["up"])
        assert np.degrees(np.arctan2(np.linalg.norm(np.cross(u, r)), u @ r)) < 0.01
    assert sure >= 2


def test_pt2_holds_the_models_own_up_estimate(tmp_path):
    model, cam = _deeplab(1), _pinhole()
    before = dict(model.named_buffers())
    info = export_model(model, cam, tmp_path / "seg.pt2", up=None)
    after = dict(model.named_buffers())  # the buffers it left out of the file are restored
    assert all(after[k] is t for k, t in before.items())
    everything = sum(t.numel() * t.element_size() for t in after.values())
    assert info["bytes"] < everything
    assert info["format"] == "torch.export" and info["inputs"] == ["image uint8 [30, 40, 3] RGB"]
    image = _room_image(cam, 3)
    run = load_exported(tmp_path / "seg.pt2")
    # the fast forms' tables (CSR parts of the jets' operators and their transposes, the
    # convolutions' tiles) are in the file as one element each, not as the model holds them
    fast = ("op_val", "op_t_val", "op_col", "op_t_col", "row0", "col0", "crow0")
    held = {k: t.untyped_storage().nbytes() for k, t in _load_pt2(tmp_path / "seg.pt2")[0]
            .named_buffers() if k.rsplit(".", 1)[-1] in fast}
    own = {k: t.numel() for k, t in after.items() if k.rsplit(".", 1)[-1] in fast}
    assert len(held) >= 10 and max(held.values()) <= 8 and min(own.values()) > 1
    assert run.metadata["up"] == "estimate" and run.metadata["task"] == "seg"
    with pytest.raises(ValueError, match=r"shape \(30, 40\); .* takes uint8 \[30, 40, 3\]"):
        run(image[..., 0])  # a gray frame: three equal channels go in
    labels, u = run(image)
    ref = segment_image(model, image, cam)
    seen = ref["labels"] != UNSEEN
    assert (labels[seen] == ref["labels"][seen]).mean() > 0.99
    u, r = np.asarray(u, np.float64), np.asarray(ref["up"])
    assert np.degrees(np.arctan2(np.linalg.norm(np.cross(u, r)), u @ r)) < 0.01


def test_pt2_holds_the_up_estimates_sign_check(tmp_path):
    """A sign check on the estimate (a fisheye sees enough of the sphere to ask it) is in
    the program: its up is usf-graph's with the check, turned where the check turns it."""
    from usf_graph.models import SignCheck, set_sign_check

    model, cam = _deeplab(1), _fisheye(40)
    with torch.no_grad():  # an untrained head's scores tie: sharpen them
        model.gravity.head.score.weight.mul_(3000.0)
    torch.manual_seed(0)
    check = SignCheck(level=3, channels=(4, 6)).eval()
    set_sign_check(model, check)
    info = export_model(model, cam, tmp_path / "seg.pt2", up=None)
    assert info["check"]["agree"] >= 0.99 and info["check"]["up_angle_deg"] < 0.01
    run = load_exported(tmp_path / "seg.pt2")
    assert json.loads(run.metadata["estimate"]) == {"level_prior": 0.0, "sign_check": True}
    turned = 0
    for seed in (4, 2):  # the check turns room 4's estimate and keeps room 2's
        image = _room_image(cam, seed)
        _, u = run(image)
        want = segment_image(model, image, cam)["up"]
        set_sign_check(model, None)
        bare = segment_image(model, image, cam)["up"]
        set_sign_check(model, check)
        np.testing.assert_allclose(u, want, atol=1e-5)
        turned += bool(np.allclose(want, -np.asarray(bare), atol=1e-9))
    assert turned == 1


def test_unread_buffers_leave_the_file_and_shared_ones_keep_what_is_read(tmp_path):
    """A .pt2 holds the buffers its graph never reads as one element each; where two names
    share a tensor (export reads it through one of them), what is read survives the file."""
    from usf_graph.train.export import _empty_unread_buffers, _quiet_exporters

    class Twins(torch.nn.Module):
        def __init__(self):
            super().__init__()
            t = torch.arange(6.0)
            self.register_buffer("read", t)
            self.register_buffer("twin", t)
            self.register_buffer("unread", torch.ones(1000), persistent=False)

        def forward(self, x):
            return x + self.read

    program = torch.export.export(Twins(), (torch.zeros(6),))
    _empty_unread_buffers(program)
    with _quiet_exporters():  # torch's note on the emptied tensors' storage
        torch.export.save(program, tmp_path / "m.pt2")
    loaded = torch.export.load(tmp_path / "m.pt2").module()
    torch.testing.assert_close(loaded(torch.ones(6)), torch.arange(1.0, 7.0))
    sizes = sorted(b.untyped_storage().nbytes() for b in loaded.buffers())
    assert sizes == [4, 4, 24]  # the unread one and one twin emptied, the twin read kept


def test_a_fixed_up_and_a_model_without_gravity(tmp_path):
    cam = _fisheye(40)
    info = export_model(_deeplab(2, gray=True), cam, tmp_path / "level.onnx", up=[0, 0, 2.0])
    assert info["inputs"] == ["image uint8 [40, 40, 3] RGB"]  # the up is a constant
    torch.manual_seed(3)
    iso = SphericalUNet(num_classes=4, level=3, channels=(4, 6), pairs=0).eval()
    info = export_model(iso, cam, tmp_path / "iso.onnx")  # no up to read
    labels, u = load_exported(tmp_path / "iso.onnx")(_room_image(cam, 4))
    assert u.shape == (3,) and np.isnan(u).all() and (labels != UNSEEN).any()


def test_refusals_name_the_fix(tmp_path):
    model, cam = _deeplab(), _fisheye(32)
    with pytest.raises(ValueError, match=r"\.onnx \(ONNX\) or \.pt2"):
        export_model(model, cam, tmp_path / "a.tflite")
    with pytest.raises(ValueError, match="up must be 'input'"):
        BoundSegmenter(model, cam, up=[0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="planar"):
        from usf_graph.models import PlanarUNet
        BoundSegmenter(PlanarUNet(num_classes=4, channels=(4, 6)), cam)
    assert not list(tmp_path.iterdir())


def _stand_in_program(monkeypatch, answer, up):
    """check_exported's exported file replaced by a program that answers ``answer`` and
    ``up`` to every call."""
    from usf_graph.train import export as ex

    monkeypatch.setattr(ex, "load_exported", lambda path, threads=None: lambda images, u=None: (answer, up))


def test_the_check_refuses_a_program_that_disagrees(tmp_path, monkeypatch):
    """check_exported against stand-in programs: one that gives usf-graph's labels passes
    with its numbers; one that relabels 2.5% of the seen pixels, or labels one unseen
    pixel, is refused as a silent wrong answer."""
    from usf_graph.train import export as ex

    model, cam = _deeplab(), _fisheye(32)
    want = segment_image(model, _room_image(cam, 0), cam, up=[0.0, 0.0, 1.0],
                         interpolation="bilinear")["labels"]
    seen = np.flatnonzero(want != UNSEEN)

    up = np.array([0.0, 0.0, 1.0], np.float32)
    _stand_in_program(monkeypatch, want.copy(), up)
    out = ex.check_exported(tmp_path / "p.onnx", model, cam, "input", "bilinear")
    assert out["agree"] == 1.0 and out["unseen_match"] and out["pixels_seen"] == len(seen)
    assert 0 <= out["load_s"] < 60 and 0 <= out["frame_s"] < 60 and out["up_angle_deg"] == 0
    relabelled = want.copy()
    relabelled.flat[seen[::40]] = (relabelled.flat[seen[::40]] + 1) % 5
    _stand_in_program(monkeypatch, relabelled, up)
    with pytest.raises(RuntimeError, match=r"disagrees .*: 97\.[45]\d% of the pixels agree, unseen pixels match"):
        ex.check_exported(tmp_path / "p.onnx", model, cam, "input", "bilinear")
    one_unseen = want.copy()
    one_unseen.flat[np.flatnonzero(want == UNSEEN)[0]] = 0
    _stand_in_program(monkeypatch, one_unseen, up)
    with pytest.raises(RuntimeError, match="100.00% of the pixels agree, unseen pixels differ"):
        ex.check_exported(tmp_path / "p.onnx", model, cam, "input", "bilinear")


def test_the_checks_verdicts_on_up_labels_and_detections(tmp_path, monkeypatch):
    """check_exported's verdicts, usf-graph and the program both stand-ins: the program's
    up estimate may differ by up to 0.01 degrees, or by more where usf-graph's is unsure
    (its margin under TIE_MARGIN: then compared given the program's up); 99% of the seen
    pixels must agree; at most one detection, or 2%, may go unmatched, and the error says
    when usf-graph's own scores tie."""
    from usf_graph.train import export as ex

    cam, path, calls = _fisheye(32), tmp_path / "p.onnx", []
    labels = np.arange(200) % 5
    labels[100:] = UNSEEN  # 100 seen pixels
    ref_up = np.array([0.0, 0.0, 1.0])

    def tilted(deg):
        return np.array([math.sin(math.radians(deg)), 0.0, math.cos(math.radians(deg))])

    def usf(margin, boxes=None):
        def reference(model, feed, camera, up=None, interpolation=None, **decoding):
            calls.append(up)
            u = ref_up if up is None else np.asarray(up, np.float64)
            return {"labels": labels, "up": u, "margin": margin, **(boxes or {})}
        monkeypatch.setattr(ex, "segment_image" if boxes is None else "detect_image", reference)

    def check(up=None, decoding=None):
        calls.clear()
        return ex.check_exported(path, object(), cam, up, "bilinear", decoding=decoding)

    usf(margin=0.5)
    for deg in (0.0, 0.008):  # the estimates agree
        _stand_in_program(monkeypatch, labels, tilted(deg))
        out = check()
        assert out["up_angle_deg"] == pytest.approx(deg, abs=1e-9) and not out["up_tie"]
        assert calls == [None] and out["agree"] == 1.0
    for margin in (0.5, ex.TIE_MARGIN):  # usf-graph is sure of its estimate: refused
        usf(margin)
        _stand_in_program(monkeypatch, labels, tilted(0.012))
        with pytest.raises(RuntimeError, match=r"reads up 0\.012 degrees away .* sure of it"):
            check()
    usf(margin=0.5 * ex.TIE_MARGIN)  # unsure: compared again, given the program's up
    out = check()
    assert out["up_tie"] and len(calls) == 2 and np.allclose(calls[1], tilted(0.012))
    usf(margin=0.5)
    for wrong, ok in ((1, True), (2, False)):  # 99 of 100 seen pixels agree: the least passed
        relabelled = labels.copy()
        relabelled[:wrong] = (relabelled[:wrong] + 1) % 5
        _stand_in_program(monkeypatch, relabelled, ref_up)
        if ok:
            assert check("input")["agree"] == 0.99
        else:
            with pytest.raises(RuntimeError, match=r"98\.00% of the pixels agree"):
                check("input")

    def boxes(n, spread=1.0):
        lon = np.linspace(-3.0, 3.0, n)  # apart: none overlaps another
        return {"boxes": np.stack([lon, 0 * lon, 0 * lon + 0.2, 0 * lon + 0.2, 0 * lon], 1),
                "classes": np.zeros(n, np.int64), "scores": np.linspace(spread, 0.0, n)}

    for n, lost, spread, ok in ((10, 1, 1.0, True), (10, 2, 1.0, False), (100, 2, 1.0, True),
                                (100, 3, 1.0, False), (10, 2, 1e-3, False), (10, 2, 5e-4, False)):
        want = boxes(n, spread)
        usf(0.5, want)
        _stand_in_program(monkeypatch, {k: v[lost:] for k, v in want.items()}, ref_up)
        if ok:
            assert check("input", {"k": n})["unmatched"] == lost
            continue
        with pytest.raises(RuntimeError, match=f"{lost} of {n} detections have no match") as err:
            check("input", {"k": n})
        assert ("is the model trained?" in str(err.value)) == (spread < 1e-3)


def test_detections_are_matched_one_to_one_by_class_overlap_and_score():
    """Each reference detection, best first, takes the free exported one of its class that
    overlaps it most; a match needs IoU >= 0.95 and scores within 1e-3. The exported
    boxes here are the reference's, nudged and in another order, plus one of another
    class and one whose score is off."""
    want = {"boxes": np.array([[0.0, 0.0, 0.4, 0.3, 0.0], [0.3, 0.1, 0.4, 0.3, 0.0],
                               [1.5, -0.2, 0.2, 0.2, 0.0], [-1.0, 0.4, 0.3, 0.3, 0.0]]),
            "classes": np.array([2, 2, 1, 0]), "scores": np.array([0.9, 0.8, 0.7, 0.6])}
    got = {"boxes": want["boxes"][[1, 0, 2, 3]] + [0.002, 0.0, 0.0, 0.0, 0.0],
           "classes": np.array([2, 2, 3, 0]), "scores": np.array([0.8, 0.9005, 0.7, 0.62])}
    r = _matched(got, want)
    assert (r["detections"], r["detections_exported"], r["matched"]) == (4, 4, 2)
    assert r["unmatched"] == 4  # two of want's and two of got's
    assert r["score_diff"] == pytest.approx(0.0005) and 0.95 <= r["iou_min"] < 1
    # more reference detections than exported ones: the rest unmatched, none reused
    few = {k: v[:1] for k, v in got.items()}
    r = _matched(few, want)
    assert (r["matched"], r["unmatched"], r["detections_exported"]) == (1, 3, 1)
    none = _matched({k: v[:0] for k, v in got.items()}, want)
    assert (none["matched"], none["unmatched"], none["iou_min"]) == (0, 4, 1.0)


def test_labels_agree_by_seen_pixels_and_a_view_of_nothing_agrees():
    want = np.array([[UNSEEN, 1, 2, 3]], np.uint8)
    got = np.array([[UNSEEN, 1, 0, 3]], np.uint8)
    assert _same_labels(got, want, rig=False) == {"pixels_seen": 3, "agree": 2 / 3, "unseen_match": True}
    r = _same_labels([got, np.full_like(want, UNSEEN)], [want, np.full_like(want, UNSEEN)], rig=True)
    assert r == {"pixels_seen": 3, "agree": 2 / 3, "unseen_match": True}
    blind = np.full_like(want, UNSEEN)
    assert _same_labels(blind, blind, rig=False) == {"pixels_seen": 0, "agree": 1.0, "unseen_match": True}
    assert not _same_labels(got, blind, rig=False)["unseen_match"]


def test_the_checks_up_angle():
    """The check's angle between the program's up and usf-graph's: in radians, 0 where
    the model reads no up (the program's is NaN, usf-graph's None)."""
    assert _angle([1.0, 0.0, 0.0], [0.0, 2.0, 0.0]) == pytest.approx(math.pi / 2)
    assert _angle([0.0, 0.6, 0.8], [0.0, -0.6, -0.8]) == pytest.approx(math.pi)
    assert _angle([0.0, 0.0, 1.0], [0.0, 0.0, 1.0]) == 0.0
    assert _angle([math.nan] * 3, None) == 0.0 and _angle([math.nan] * 3, [0.0, 0.0, 1.0]) == 0.0


def test_onnx_without_its_packages_names_the_extra_to_install(tmp_path, monkeypatch):
    """Without onnxscript an ONNX export is refused before any work, without onnxruntime
    an ONNX file is not run; both name ``usf-graph[export]``."""
    monkeypatch.setitem(sys.modules, "onnxscript", None)  # import then raises ImportError
    with pytest.raises(ImportError, match=r"onnxscript: pip install 'usf-graph\[export\]'"):
        export_model(_deeplab(), _fisheye(32), tmp_path / "a.onnx", check=False)
    monkeypatch.setitem(sys.modules, "onnxruntime", None)
    (tmp_path / "b.onnx").write_bytes(b"")
    with pytest.raises(ImportError, match=r"needs onnxruntime: pip install 'usf-graph\[export\]'"):
        load_exported(tmp_path / "b.onnx")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.onnx"]


def test_a_failed_export_leaves_no_file(tmp_path, monkeypatch):
    def fail(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(torch.export, "save", fail)
    with pytest.raises(RuntimeError, match="disk full"):
        export_model(_deeplab(), _fisheye(32), tmp_path / "a.pt2", up="input", check=False)
    assert not list(tmp_path.iterdir())


def test_a_cameras_share_weighs_what_it_lifts():
    """CameraIO with fractional shares (a feathered blend) lifts share * the frontend's
    lift of the image in [0, 1]; a zero share drops the point."""
    fe = SphericalFrontend(_fisheye(24), icosahedral(2), "bilinear")
    g = torch.Generator().manual_seed(3)
    share = torch.rand(fe.num_points, generator=g, dtype=torch.float64)
    share[::3] = 0.0
    image = torch.randint(0, 256, (24, 24, 3), generator=g, dtype=torch.uint8)
    io = CameraIO(fe, share, render=False)
    want = share[:, None].float() * fe.lift(image.numpy().astype(np.float32) / 255)
    torch.testing.assert_close(io.lift(image), want, atol=1e-6, rtol=1e-5)
    assert fe.mask[1::3].any() and not io.lift(image)[::3].any()


def test_a_rig_is_one_program_with_an_image_and_labels_per_camera(tmp_path):
    """Two back-to-back fisheyes: one sphere, blended as RigFrontend blends them, and each
    camera's labels as segment_image gives them for the rig."""
    front = _fisheye(36)
    back = front.with_rotation(np.diag([-1.0, -1.0, 1.0]) @ front.rotation)
    rig = {"front": front, "back": back}
    model = _deeplab(4)
    with warnings.catch_warnings():  # the oriented kernels' kept basis is read, not re-stored
        warnings.filterwarnings("error", message=".*assigned during export")
        info = export_model(model, rig, tmp_path / "rig.onnx", up="input")
    assert info["inputs"] == ["front uint8 [36, 36, 3] RGB", "back uint8 [36, 36, 3] RGB",
                              "up float32 [3]"]
    assert info["outputs"] == ["labels_front", "labels_back", "up_read"]
    assert info["check"]["agree"] >= 0.99
    room = make_room(5)
    images = [render(room, c, boxes=False).rgb for c in (front, back)]
    labels, _ = load_exported(tmp_path / "rig.onnx")(images, [0.0, 0.0, 1.0])
    ref = segment_image(model, images, rig, up=[0.0, 0.0, 1.0])["labels"]
    for got, want in zip(labels, ref):
        seen = want != UNSEEN
        assert np.array_equal(got == UNSEEN, ~seen) and (got[seen] == want[seen]).mean() > 0.99
    swapped = segment_image(model, images[::-1], rig, up=[0.0, 0.0, 1.0])["labels"][0]
    assert (swapped != ref[0]).mean() > 0.05  # the cameras' order matters: a test that can fail


def _detector(seed=0):
    """A small upright detector whose heatmaps peak here and there over a room (at
    initialization CenterNet's prior keeps every score near 0.01)."""
    torch.manual_seed(seed)
    model = SphericalDetector(num_classes=3, input_level=3, head_level=2, min_level=1,
                              channels=(4, 6, 8), pairs=2, gradient_fields=2, gravity=True,
                              upright=True, up_fields=2, upright_convs=2).eval()
    with torch.no_grad():
        model.head.weight[:3].mul_(30.0)
        model.head.bias[:3].fill_(-1.0)
    return model


def _same_detections(got, want):
    assert len(want["boxes"]) > 3 and len(got["boxes"]) == len(want["boxes"])
    assert np.array_equal(got["classes"], want["classes"])
    np.testing.assert_allclose(got["scores"], want["scores"], rtol=0, atol=1e-5)
    np.testing.assert_allclose(got["boxes"][:, 2:4], want["boxes"][:, 2:4], rtol=0, atol=1e-4)
    centres = [from_latlon(b[:, 1], b[:, 0]) for b in (got["boxes"], want["boxes"])]
    assert np.abs(centres[0] - centres[1]).max() < 1e-4
    # the axes of a square box at the zenith, where an upright model's spin fields vanish,
    # are ill-conditioned: float32 turns them by up to a degree (IoU 0.99)
    assert float(box_iou(got["boxes"], want["boxes"], dtype=torch.float64).min()) > 0.98


def test_a_detector_exported_finds_usf_graphs_boxes(tmp_path):
    model, cam = _detector(), _fisheye(40)
    decoding = dict(k=40, nms=0.2, drop_hidden=False)  # boxes the view cuts, overlapping
    info = export_model(model, cam, tmp_path / "det.onnx", up="input", **decoding)
    assert info["outputs"] == ["boxes", "classes", "scores", "up_read"]
    assert info["check"]["unmatched"] == 0 and info["check"]["matched"] > 3
    run = load_exported(tmp_path / "det.onnx")
    meta = run.metadata
    assert meta["task"] == "det" and json.loads(meta["classes"]) == [f"class {k}" for k in range(3)]
    assert json.loads(meta["decoding"]) == {"threshold": 0.05, **decoding}
    for seed, up in ((1, [0.0, 0.0, 1.0]), (2, [0.3, -0.2, 0.9])):  # new rooms, a tilted up
        image = _room_image(cam, seed)
        got, u = run(image, up)
        want = detect_image(model, image, cam, up=up, **decoding)
        _same_detections(got, want)
        assert np.allclose(u, np.asarray(up) / np.linalg.norm(up), atol=1e-6)
        # NMS was at work, and the boxes centred where the camera does not see were kept
        assert len(detect_image(model, image, cam, up=up, **{**decoding, "nms": None})["boxes"]) \
            > len(want["boxes"]) > len(detect_image(model, image, cam, up=up, k=40, nms=0.2)["boxes"])
    got, u = run(image, [math.nan, 0.0, 1.0])  # no raising in a program: no detections
    assert len(got["boxes"]) == 0 and np.isnan(u).all()


def test_a_detector_on_a_rig_with_its_own_up_estimate_as_pt2(tmp_path):
    front = _fisheye(36)
    rig = [front, front.with_rotation(np.diag([-1.0, -1.0, 1.0]) @ front.rotation)]
    model = _detector(1)
    info = export_model(model, rig, tmp_path / "det.pt2", up=None, k=30, nms=0.3)
    assert info["inputs"] == ["cam0 uint8 [36, 36, 3] RGB", "cam1 uint8 [36, 36, 3] RGB"]
    room = make_room(5)
    images = [render(room, c, boxes=False).rgb for c in rig]
    got, u = load_exported(tmp_path / "det.pt2")(images)
    want = detect_image(model, images, rig, k=30, nms=0.3)
    _same_detections(got, want)
    u, r = np.asarray(u, np.float64), np.asarray(want["up"])
    assert np.degrees(np.arctan2(np.linalg.norm(np.cross(u, r)), u @ r)) < 0.01


def test_a_detector_without_gravity_reads_no_up(tmp_path, caplog):
    torch.manual_seed(2)
    model = SphericalDetector(num_classes=3, input_level=3, head_level=2, min_level=1,
                              channels=(4, 6, 8), pairs=2, gradient_fields=2).eval()
    with torch.no_grad():
        model.head.weight[:3].mul_(300.0)
        model.head.bias[:3].fill_(-1.0)
    cam = _fisheye(40)
    info = export_model(model, cam, tmp_path / "iso.onnx", k=20, drop_hidden=False)
    assert info["inputs"] == ["image uint8 [40, 40, 3] RGB"] and info["check"]["unmatched"] == 0
    # the exporter's note on the constant NaN up stays off the screen
    assert not [r for r in caplog.records if "Skipped deduplication" in r.getMessage()]
    image = _room_image(cam, 3)
    got, u = load_exported(tmp_path / "iso.onnx")(image)
    _same_detections(got, detect_image(model, image, cam, k=20, drop_hidden=False))
    assert np.isnan(u).all()


def test_detector_refusals_name_the_fix(tmp_path):
    with pytest.raises(ValueError, match="k, nms: options of a detector's decoding"):
        export_model(_deeplab(), _fisheye(32), tmp_path / "a.onnx", k=5, nms=0.1)
    with pytest.raises(ValueError, match="not a spherical detector"):
        BoundDetector(_deeplab(), _fisheye(32))
    assert not list(tmp_path.iterdir())


def test_a_pt2_is_loaded_again_once_its_file_changes(tmp_path, monkeypatch):
    """``load_exported`` keeps the last ``.pt2`` it loaded (export's check has just loaded
    the file a caller loads next); a file written again at the same path is read anew."""
    import os

    from usf_graph.train import export

    loads = []

    class Program:
        def module(self):
            return self

        class graph:  # noqa: N801 (the program's graph: no inputs to read)
            @staticmethod
            def find_nodes(op):
                return []

    def fake_load(path, extra_files):
        loads.append(Path(path).read_text())
        extra_files[export.META_FILE] = json.dumps({"task": "seg", "version": loads[-1]})
        return Program()

    monkeypatch.setattr(torch.export, "load", fake_load)
    path = tmp_path / "m.pt2"
    path.write_text("one")
    assert load_exported(path).metadata["version"] == "one"
    assert load_exported(path).metadata["version"] == "one" and loads == ["one"]
    path.write_text("two")  # same size: told apart by its modification time
    os.utime(path, ns=(path.stat().st_atime_ns, path.stat().st_mtime_ns + 1))
    assert load_exported(path).metadata["version"] == "two" and loads == ["one", "two"]
    other = tmp_path / "n.pt2"
    other.write_text("three")
    assert load_exported(other).metadata["version"] == "three"
    assert load_exported(path).metadata["version"] == "two" and len(loads) == 4  # one kept
