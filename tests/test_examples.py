"""The README's examples run, and what they print holds."""

import json

import numpy as np
import pytest
import torch

from tests.helpers import load_script


def load(name):
    return load_script(f"examples/{name}.py")


def test_pointcloud_example_small_run(tmp_path):
    ex = load("pointcloud_se3")
    res = ex.main(["--out", str(tmp_path), "--per-class", "2", "--points", "96", "--epochs", "1",
                   "--no-progress"])
    saved = json.loads((tmp_path / "results.json").read_text())
    assert saved == res
    # distances only: a rigid motion cannot change a single prediction
    pc = res["PointCloudNet"]
    assert pc["unmoved"] == pc["rigidly moved"]
    assert set(res) == {"PointCloudNet", "PointNet (raw xyz)", "seconds"}


def test_lens_normal_maps_example_writes_its_figures(tmp_path):
    ex = load("lens_normal_maps")
    ex.main(["--out", str(tmp_path)])
    pngs = sorted(p.name for p in tmp_path.glob("*.png"))
    assert "fisheye_from_pano.png" in pngs and len(pngs) >= len(ex.example_cameras()) + 1
    assert all((tmp_path / p).stat().st_size > 10_000 for p in pngs)


@pytest.mark.slow
def test_pointcloud_example_full_table(tmp_path):
    """The README's table (about 1 minute): distances only lose nothing under rigid motions,
    the raw-coordinate baseline loses most of its accuracy."""
    res = load("pointcloud_se3").main(["--out", str(tmp_path), "--no-progress"])
    pc, pn = res["PointCloudNet"], res["PointNet (raw xyz)"]
    assert pc["unmoved"] >= 0.9 and pc["unmoved"] - pc["rigidly moved"] < 0.01
    assert pn["unmoved"] >= 0.9 and pn["unmoved"] - pn["rigidly moved"] > 0.5


def test_seg_height_cue_example_small_run(tmp_path):
    ex = load("seg_height_cue")
    pos = torch.nn.functional.normalize(torch.randn(7, 3, dtype=torch.float64), dim=-1)
    x = torch.rand(2, 7, 3, dtype=torch.float64)
    h = ex.with_true_height(x, pos)
    assert torch.equal(h[..., :3], x) and torch.equal(h[0, :, 3], pos[:, 2])
    res = ex.main(["--root", str(tmp_path), "--epochs", "1", "--size", "16", "--level", "3",
                   "--num-train", "8", "--num-test", "2", "--no-progress"])
    assert set(res) == {"plain", "gravity", "true_height"}
    assert all(0 <= r["sphere_mIoU"] <= 1 for r in res.values())
    assert 0 <= res["gravity"]["up_err_median_deg"] <= 180
    assert 0 <= res["gravity"]["sphere_mIoU_true_up"] <= 1


def test_up_estimate_example_small_run(tmp_path):
    ex = load("up_estimate")
    res = ex.main(["--root", str(tmp_path), "--epochs", "1", "--size", "16", "--level", "3",
                   "--num-train", "4", "--num-test", "2", "--caps", "0.5", "--no-progress"])
    assert set(res) == {"seconds", "train", "a", "c", "d"}
    for k in ("train", "a", "c", "d"):
        r = res[k]
        assert r["views"] == (4 if k == "train" else 2)
        assert 0 <= r["median_deg"] <= r["p90_deg"] <= 180 and 0 <= r["over_60deg"] <= r["views"]
        assert 0 <= r["head_median_deg"] <= 180
        assert 0 <= r["over_60deg_unsure"] <= min(r["over_60deg"], r["unsure"]) <= r["views"]
    # the errors are the angles to +z of what the estimate returns
    err = ex.up_errors(lambda x, m: {"up": torch.tensor([[0.0, 1.0, 0.0]]).expand(len(x), 3)},
                       type("DS", (), {"x": torch.zeros(3, 5, 3), "mask": torch.ones(3, 5, dtype=torch.bool)}))
    assert err.shape == (3,) and abs(err - 90).max() < 1e-4


def test_field_of_view_example_feeds_its_inputs():
    """Input 4 is the lens's image inside its field of view and the panorama outside; 5 the
    lens's image with every hidden point the colour of the nearest seen one; the masks are
    none, the lens's, the lens's, none, none; 6 reads the up estimated from the lens."""
    ex = load("field_of_view")
    pano, lens = torch.rand(2, 6, 3), torch.rand(2, 6, 3)
    seen = torch.tensor([True, False, True, True, False, False])
    pos = torch.tensor([[1.0, 0, 0], [0.9, 0.1, 0], [0, 1, 0], [0, 0, 1], [0, 0.2, 0.9], [0, 0.9, 0.1]])
    nearest = ex.nearest_seen(pos, seen)
    assert nearest.tolist() == [0, 0, 2, 3, 3, 2]
    calls = []
    res = ex._inputs(pano, lens, seen, lambda x, m, up=None: calls.append((x, m, up)) or len(calls),
                     nearest, lens_up="u")
    assert list(res.values()) == [1, 2, 3, 4, 5, 6]
    (x1, m1, _), (x2, m2, _), (x3, m3, _), (x4, m4, _), (x5, m5, u5), (x6, m6, u6) = calls
    assert x1 is pano and m1 is None and x2 is pano and m2 is seen and x3 is lens and m3 is seen
    assert m4 is None and torch.equal(x4[:, seen], lens[:, seen]) and torch.equal(x4[:, ~seen], pano[:, ~seen])
    assert m5 is None and u5 is None and torch.equal(x5, lens[:, [0, 0, 2, 3, 3, 2]])
    assert torch.equal(x6, x5) and m6 is None and u6 == "u"


@pytest.mark.parametrize("kind", ["seg", "det"])
def test_field_of_view_example_small_run(tmp_path, kind):
    from usf_graph.models import SphericalDetector
    from usf_graph.train.engine import save_checkpoint
    from usf_graph.train.seg import make_model

    torch.manual_seed(0)
    if kind == "seg":
        net = make_model("spherical_unet", level=3)
        cfg = {"model": "spherical_unet", "size": 16, **net.config}
    else:
        net = SphericalDetector(num_classes=12, gravity=True, upright=True)
        cfg = net.config
    save_checkpoint(tmp_path / "net.pt", net, cfg, {})
    res = load("field_of_view").main([str(tmp_path / "net.pt"), "--root", str(tmp_path / "rooms"),
                                      "--num-test", "2"]
                                     + (["--size", "32"] if kind == "det" else ["--known-up"]))
    # the detector reads its estimate: then a sixth input, up from the lens's image
    assert len(res) == (6 if kind == "det" else 5) and all(0 <= v <= 1 for v in res.values())


def test_up_sign_example_small_run(tmp_path, capsys):
    """The sign check trains on a few views and is asked on (a), (c) and (d): every view
    it flips gets exactly the opposite up, the printed counts are the returned ones, and
    ``--save`` writes a check that ``load_sign_check`` reads back."""
    from usf_graph.train.engine import save_checkpoint
    from usf_graph.train.seg import make_model
    from usf_graph.train.sign import load_sign_check

    torch.manual_seed(0)
    net = make_model("spherical_unet", level=3)
    save_checkpoint(tmp_path / "net.pt", net, {"model": "spherical_unet", "size": 16, **net.config}, {})
    ex = load("up_sign")
    res = ex.main([str(tmp_path / "net.pt"), "--root", str(tmp_path / "rooms"), "--num-train", "4",
                   "--num-test", "2", "--epochs", "1", "--cut-epochs", "1", "--no-progress",
                   "--save", str(tmp_path / "sign.pt")])
    out = capsys.readouterr().out
    assert set(res) == {"a", "c", "d"}
    for k, r in res.items():
        assert 0 <= r["flipped"] <= 2
        assert all(0 <= r[w]["gross"] <= 2 and 0 <= r[w]["mIoU"] <= 1 for w in ("before", "after"))
        if not r["flipped"]:
            assert r["after"] == r["before"]
        assert f"({k}) gross errors {r['before']['gross']} -> {r['after']['gross']} ({r['flipped']} flipped)" in out
    sign = load_sign_check(tmp_path / "sign.pt")
    assert sign.config["level"] == 3 and f"sign check: {tmp_path / 'sign.pt'}" in out
    # the example's own flips: exactly the opposite up, where the check scores it higher
    sets = ex.seg.protocol_sets(tmp_path / "rooms", 16, 3, 0, 2, tests=("c",), progress=False)
    net.eval()
    up, fixed = ex.checked(sign, net, sets["c"])
    same, opposite = torch.isclose(fixed, up).all(-1), torch.isclose(fixed, -up).all(-1)
    assert (same | opposite).all()
    x, mask = sets["c"].x.float(), sets["c"].mask[0]
    with torch.no_grad():
        assert torch.equal(opposite, sign.score(x, mask, -up) > sign.score(x, mask, up))


def test_up_sign_example_refuses_a_planar_checkpoint(tmp_path):
    from usf_graph.models import PlanarUNet
    from usf_graph.train.engine import save_checkpoint

    save_checkpoint(tmp_path / "p.pt", PlanarUNet(13), {"model": "planar_unet", "size": 16}, {})
    with pytest.raises(ValueError, match="not a spherical seg model"):
        load("up_sign").main([str(tmp_path / "p.pt")])


@pytest.mark.parametrize("kind", ["seg", "det"])
def test_through_lens_example_trains_the_first_phase_through_the_lens(tmp_path, kind):
    """It starts from the first phase (``<checkpoint>/last.pt``), not the final weights:
    with 0 epochs it scores exactly what that state scores. With 1 epoch the network
    trains through the lens while its up estimate stays frozen, and the result is saved
    with its scores. A checkpoint without a first phase is refused."""
    from usf_graph.models import set_level_prior
    from usf_graph.train import det, seg, seg_eval
    from usf_graph.train.engine import load_checkpoint, save_checkpoint

    torch.manual_seed(0)
    if kind == "seg":
        final, first = (seg.make_model("spherical_unet", level=3) for _ in range(2))
        cfg, size = {"model": "spherical_unet", "size": 16, **final.config}, []
    else:
        from usf_graph.models import SphericalDetector

        final, first = (SphericalDetector(num_classes=12, gravity=True, upright=True) for _ in range(2))
        cfg, size = final.config, ["--size", "32", "--rendered", "4"]
    save_checkpoint(tmp_path / "net.pt", final, cfg, {})
    save_checkpoint(tmp_path / "net" / "last.pt", first, cfg, {})
    ex = load("through_lens")
    common = [str(tmp_path / "net.pt"), "--root", str(tmp_path / "rooms"), "--num-train", "4",
              "--num-test", "2", "--no-progress", *size]
    res = ex.main(common + ["--epochs", "0"])
    first.eval()
    if kind == "seg":
        sets = seg.protocol_sets(tmp_path / "rooms", 16, 3, 0, 2, tests=("a", "d"), progress=False)
        for known, key in ((True, "true up"), (False, "estimate")):
            want, _ = seg_eval.evaluate_protocol(first, sets, ("a", "d"), False, known_up=known)
            assert res[key] == {k: r["mIoU"] for k, r in want.items()}
        set_level_prior(first, 10.0)  # the third row: the estimate with a level camera's prior
        want, _ = seg_eval.evaluate_protocol(first, sets, ("a", "d"), False)
        assert res["estimate, level prior"] == {k: r["mIoU"] for k, r in want.items()}
    else:
        sets = det.protocol_sets(tmp_path / "rooms", 32, num_train=0, num_test=2, progress=False)
        data = det.DetectionSet.spherical(sets["d"])
        want = det.score(det.predict(first, data, progress=False), data, 12)["AP50"]
        assert res["estimate"]["d"] == want
    res = ex.main(common + ["--epochs", "1", "--out", str(tmp_path / "adapted")])
    assert (tmp_path / "adapted" / "second_phase" / "metrics.csv").exists()
    saved = load_checkpoint(tmp_path / "adapted" / "model.pt")
    assert saved["metrics"] == res and saved["config"] == cfg
    start = first.state_dict()
    moved = [k for k, v in saved["state_dict"].items() if not torch.equal(v, start[k])]
    assert moved and not any(k.startswith("gravity.") for k in moved)
    with pytest.raises(SystemExit, match="no first-phase state"):
        ex.main([str(tmp_path / "adapted" / "model.pt")])


def test_planar_on_lens_example_trains_and_scores_on_the_lens_own_images(tmp_path):
    """The planar U-Net trains on the pinhole's own images and is scored on them, not on
    panoramas re-imaged: its saved weights, run by hand on the test's images, give the
    printed score. On rooms with materials by kind, which it renders and scores on."""
    from usf_graph.datasets import RoomsSegmentation
    from usf_graph.train import seg, seg_metrics
    from usf_graph.train.checkpoints import load_protocol_model

    out = tmp_path / "out"
    res = load("planar_on_lens").main(["--test", "d", "--num-train", "3", "--epochs", "1",
                                       "--size", "16", "--level", "3", "--num-test", "2",
                                       "--root", str(tmp_path / "rooms"), "--out", str(out),
                                       "--no-progress", "--materials", "by_kind"])
    ckpt = load_protocol_model(out / "model.pt")
    assert (ckpt.name, ckpt.size, res["materials"]) == ("planar_unet", 16, "by_kind")
    assert ckpt.metrics == res
    assert json.loads((out / "results.json").read_text()) == res
    assert len((out / "metrics.csv").read_text().splitlines()) == 2  # one epoch logged
    test = seg.protocol_sets(tmp_path / "rooms", 16, 3, 0, 2, tests=("d",), progress=False,
                             materials="by_kind")["d"]
    assert test.image.shape[1:3] == (16, 16)
    with torch.no_grad():
        logits = ckpt.model.eval()(test.image.permute(0, 3, 1, 2).float() / 255)
    want = seg_metrics.score(logits.argmax(1).to(torch.uint8).numpy(), test)
    assert res["mIoU"] == want["mIoU"] and res["mAcc"] == want["mAcc"]
    # the one training split it rendered is the pinhole's
    rendered = sorted((tmp_path / "rooms" / "processed").glob("rooms_train_*"))
    train = RoomsSegmentation(tmp_path / "rooms", "train", camera=test.camera,
                              grid="icosahedral:3", num_scenes=3, progress=False,
                              materials="by_kind")
    assert [str(f) for f in rendered] == train.processed_paths


def test_up_by_view_example_counts_each_view_once_and_scores_as_the_protocol(tmp_path, capsys):
    """Its bins hold every view once and their gross errors are up_report's; on all views its
    AP50 is the protocol's score, with the estimate and with the true up; the share of floor
    and ceiling is read off the label image."""
    from usf_graph.models import SphericalDetector
    from usf_graph.scenes import SEMANTIC_CLASSES
    from usf_graph.train import det
    from usf_graph.train.engine import save_checkpoint
    from usf_graph.train.gravity import up_report, views_up

    torch.manual_seed(0)
    net = SphericalDetector(num_classes=12, gravity=True, upright=True)
    save_checkpoint(tmp_path / "net.pt", net, {**net.config, "size": 32}, {})
    ex = load("up_by_view")
    res = ex.main([str(tmp_path / "net.pt"), "--root", str(tmp_path / "rooms"), "--num-test", "3"])
    ds = det.protocol_sets(tmp_path / "rooms", 32, num_train=0, num_test=3, progress=False)["d"]
    assert sum(b["views"] for b in res["bins"]) == 3
    want = up_report(net.eval().gravity, ds.x, ds.mask[0], views_up(ds))
    assert sum(b["gross"] for b in res["bins"]) == want["gross"]
    assert all(b["upside_down"] <= b["gross"] for b in res["bins"])
    data = det.DetectionSet.spherical(ds)
    for name, up in (("estimate", None), ("true up", views_up(ds))):
        score = det.score(det.predict(net, data, progress=False, up=up), data, 12)["AP50"]
        assert res["AP50"][name]["all"] == pytest.approx(score)
    out = capsys.readouterr().out  # these 3 views all show floor or ceiling: no close-ups
    assert "the rest" in out and "wall close-ups" not in out
    assert res["bins"][0]["views"] == 0
    # AP50 on a subset of views: the truth found scores 1, a view's boxes missed score 0
    pano = det.DetectionSet.spherical(det.protocol_sets(tmp_path / "rooms", 32, num_train=0,
                                                        num_test=3, progress=False)["a"])
    found = [dict(zip(("boxes", "classes"), pano.truth(i)), scores=np.ones(len(pano.truth(i)[0])))
             for i in range(3)]
    n = [len(pano.truth(i)[0]) for i in range(3)]
    assert ex.ap50_on(found, pano, [0, 1, 2], 12) == (pytest.approx(1.0), sum(n))
    first = next(i for i in range(3) if n[i])
    found[first] = {k: v[:0] for k, v in found[first].items()}
    assert ex.ap50_on(found, pano, [first], 12)[0] == 0.0
    rest = [i for i in range(3) if i != first and n[i]]
    assert ex.ap50_on(found, pano, rest, 12)[0] == pytest.approx(1.0)
    floor, ceiling, wall = (SEMANTIC_CLASSES.index(c) for c in ("floor", "ceiling", "wall"))
    labels = torch.tensor([[[floor, wall], [wall, wall]], [[ceiling, floor], [floor, 255]]])
    np.testing.assert_allclose(ex.floor_and_ceiling(_Sized(labels)), [0.25, 0.75])


def test_up_by_view_example_scores_a_segmenter_as_the_protocol(tmp_path):
    """For a seg checkpoint, mIoU over all views is the protocol's score of the test, with
    the estimate and with the true up, and the bins hold every view once."""
    from usf_graph.train import seg, seg_eval, seg_metrics
    from usf_graph.train.engine import save_checkpoint
    from usf_graph.train.gravity import views_up

    torch.manual_seed(0)
    net = seg.make_model("spherical_unet", level=3)
    save_checkpoint(tmp_path / "net.pt", net, {"model": "spherical_unet", "size": 16, **net.config}, {})
    res = load("up_by_view").main([str(tmp_path / "net.pt"), "--root", str(tmp_path / "rooms"),
                                   "--num-test", "3"])
    ds = seg.protocol_sets(tmp_path / "rooms", 16, 3, num_train=0, num_test=3, tests=("d",),
                           progress=False)["d"]
    assert sum(b["views"] for b in res["bins"]) == 3
    for name, up in (("estimate", None), ("true up", views_up(ds))):
        want = seg_metrics.score(seg_eval.predict(net.eval(), ds, progress=False, up=up)[0], ds)["mIoU"]
        assert res["mIoU"][name]["all"] == pytest.approx(want)


class _Sized:
    """A stand-in split with only a label image."""

    def __init__(self, label_image):
        self.label_image = label_image

    def __len__(self):
        return len(self.label_image)


def test_deploy_onnx_example_runs_an_exported_file_without_usf_graph(tmp_path, capsys):
    """The example reads frames from disk (BGR), runs the exported program, and writes the
    labels the program gives for the RGB frame; it names classes from the file itself."""
    import cv2

    pytest.importorskip("onnxruntime")
    from usf_graph.cameras import KannalaBrandt
    from usf_graph.models import SphericalUNet
    from usf_graph.train.export import export_model, load_exported

    cam = KannalaBrandt(10.0, 10.0, 15.5, 11.5, 32, 24, k=(0.0, 0.0, 0.0, 0.0)).with_fov(180)
    torch.manual_seed(0)
    model = SphericalUNet(13, level=3, channels=(4, 4), gravity=True, pairs=0).eval()
    export_model(model, cam, tmp_path / "seg.onnx", up="input", check=False)
    rgb = np.random.default_rng(1).integers(0, 256, (24, 32, 3), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "frame.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    ex = load("deploy_onnx")
    args = [str(tmp_path / "seg.onnx"), str(tmp_path / "frame.png"), "--out", str(tmp_path / "o")]
    assert ex.main([*args, "--up", "0", "0", "1"]) == 0
    printed = capsys.readouterr().out
    assert printed.startswith("frame: ") and "%" in printed and "up read [0.0, 0.0, 1.0]" in printed
    got = cv2.imread(str(tmp_path / "o" / "frame_labels.png"), cv2.IMREAD_UNCHANGED)
    want, _ = load_exported(tmp_path / "seg.onnx")(rgb, [0.0, 0.0, 1.0])
    assert np.array_equal(got, want) and (got == 255).any() and (got != 255).any()
    assert (tmp_path / "o" / "frame_overlay.png").exists()
    with pytest.raises(SystemExit, match="give --up"):
        ex.main(args)


def test_deploy_onnx_example_writes_an_exported_detectors_boxes(tmp_path, capsys):
    """A detector's file: the example writes the program's detections, named, in radians
    and in PANDORA's degrees (as usf-graph's own to_pandora gives them)."""
    import json

    import cv2

    pytest.importorskip("onnxruntime")
    from usf_graph.cameras import KannalaBrandt
    from usf_graph.models import SphericalDetector
    from usf_graph.ops import to_pandora
    from usf_graph.train.export import export_model, load_exported

    cam = KannalaBrandt(10.0, 10.0, 15.5, 11.5, 32, 24, k=(0.0, 0.0, 0.0, 0.0)).with_fov(180)
    torch.manual_seed(0)
    model = SphericalDetector(num_classes=12, input_level=3, head_level=2, min_level=1,
                              channels=(4, 6, 8), pairs=2, gradient_fields=2).eval()
    with torch.no_grad():  # heatmaps that peak above the threshold here and there
        model.head.weight[:12].mul_(30.0)
        model.head.bias[:12].fill_(-1.0)
    export_model(model, cam, tmp_path / "det.onnx", check=False, k=20, drop_hidden=False)
    rgb = np.random.default_rng(1).integers(0, 256, (24, 32, 3), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "frame.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    out = tmp_path / "o"
    assert load("deploy_onnx").main([str(tmp_path / "det.onnx"), str(tmp_path / "frame.png"),
                                     "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    found = json.loads((out / "frame_boxes.json").read_text())
    run = load_exported(tmp_path / "det.onnx")
    want, _ = run(rgb)
    assert len(found) == len(want["boxes"]) > 0 and f"({len(found)} detections)" in printed
    names = [d["class"] for d in found]
    assert names == [json.loads(run.metadata["classes"])[c] for c in want["classes"]]
    assert names[0] in printed and len(set(names)) > 1
    np.testing.assert_allclose([d["box_rad"] for d in found], want["boxes"], atol=1e-6)
    np.testing.assert_allclose([d["pandora_deg"] for d in found], to_pandora(want["boxes"]), atol=2e-3)


def test_rig_parallax_example_small_run(tmp_path):
    """One room: the centred rig is the floor, and stitching near the room's depth beats
    ignoring a 0.15 m baseline."""
    from tests.helpers import tiny_seg_checkpoint

    tiny_seg_checkpoint(tmp_path / "seg.pt")
    res = load("rig_parallax").main(["--out", str(tmp_path), "--rooms", "1", "--level", "4",
                                     "--size", "96", "--no-progress", "--checkpoint",
                                     str(tmp_path / "seg.pt")])
    assert set(res["model"]) == {"cameras at the centre", "at infinity", "stitched at 2 m",
                                 "stitched where the seams agree"}
    assert all(0 <= v <= 1 for v in res["model"].values())
    s = res["settings"]
    assert json.loads((tmp_path / "results.json").read_text()) == res
    assert (tmp_path / "seams.png").stat().st_size > 10_000
    assert list(s)[:2] == ["no baseline (the floor)", "at infinity"] and len(s) == 7
    assert len(res["chosen_m"]) == 1 and "stitched where the seams agree" in s
    floor, inf, two = s["no baseline (the floor)"], s["at infinity"], s["stitched at 2 m"]
    assert floor["labels_wrong"] < two["labels_wrong"] < inf["labels_wrong"]
    assert floor["colour_err_seams"] < two["colour_err_seams"] < inf["colour_err_seams"]


def test_level_panorama_example_levels_a_tilted_room(tmp_path, capsys):
    ex = load("level_panorama")
    res = ex.run(tmp_path, pitch=-12.0, roll=9.0, size=256)
    assert abs(res["tilt_deg"] - 15.0) < 0.5  # about 12 and 9 degrees together
    assert res["up_error_deg"] < 1.0
    assert res["pixel_error_leveled"] < 0.3 * res["pixel_error_tilted"]
    assert (tmp_path / "tilted.png").exists() and (tmp_path / "level.jpg").exists()
    assert f"up from the lines {res['up_error_deg']:.2f} degrees off" in capsys.readouterr().out


def test_level_panorama_survey_scores_each_lens_on_tilted_rooms(capsys):
    ex = load("level_panorama")
    errors = ex.survey(size=128, rooms=2)
    assert set(errors) == {"panorama", "fisheye 190", "pinhole 90"}
    assert all(len(e) == 2 for e in errors.values())
    assert errors["panorama"][1] < 1.5  # a room with materials by kind, through the panorama
    assert "within 1 degree on" in capsys.readouterr().out


def test_stitch_video_example_stitches_a_dual_fisheye_video(tmp_path):
    """One frame: the video stitched at the distance the seams choose is nearer the room
    seen from the rig's centre than the video stitched at infinity, on the seam most."""
    res = load("stitch_video").main(["--out", str(tmp_path), "--frames", "1", "--width", "256"])
    inf, auto = res["inf"], res["auto"]
    assert inf["frames"] == auto["frames"] == 1
    assert auto["mean"] < inf["mean"] and auto["seam"] < 0.8 * inf["seam"]
    assert auto["mean"] < 10  # grey levels: resampling and Motion JPEG both ways
    assert json.loads((tmp_path / "results.json").read_text()) == res
    assert (tmp_path / "stitch.png").stat().st_size > 10_000
