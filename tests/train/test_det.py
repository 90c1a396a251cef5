"""The detection protocol end to end on a few tiny rooms, and the PANDORA command on the
fixture in PANDORA's format."""

import functools
import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from usf_graph.cli import main
from usf_graph.models import SphericalDetector
from usf_graph.models.centernet import box_centres
from usf_graph.ops import share_in_view
from usf_graph.scenes import DETECTION_CLASSES
from usf_graph.train.det import (
    PROTOCOL,
    DetectionSet,
    ThroughRandomFields,
    format_table,
    predict,
    protocol_sets,
    run,
    score,
)
from usf_graph.train.det_metrics import FULLY_SEEN
from usf_graph.train.fov import camera_field
from usf_graph.train.gravity import lines_up


def test_protocol_runs_and_scores_every_test(tmp_path, capsys, monkeypatch):
    res = run(root=tmp_path / "rooms", out=tmp_path / "out", size=32, num_train=3, num_test=2,
              epochs=1, batch_size=2, progress=False, up_train=4, up_epochs=1, up_extra=2,
              fov_epochs=1, channel_scale=0.5)
    saved = json.loads((tmp_path / "out" / "results.json").read_text())
    # both detectors at half their channels, the up estimate at its own
    assert saved["channel_scale"] == 0.5
    configs = {n: torch.load(tmp_path / "out" / f"{n}.pt", weights_only=True)["config"]
               for n in ("spherical", "planar")}
    assert configs["spherical"]["channels"] == [16, 32, 64, 64]  # of 32, 64, 128, 128
    assert configs["planar"]["channels"] == [8, 16, 32, 64]  # of 16, 32, 64, 128
    # the up estimate trained alone on 4 views and 2 cheap ones, then the upright detector
    # on the first 3
    assert saved["samples"] == {"train": 3, "test": 2, "up_train": 4, "up_extra": 2} and saved["upright"]
    assert len((tmp_path / "out" / "up_estimate" / "metrics.csv").read_text().splitlines()) == 2
    assert len(list((tmp_path / "rooms" / "processed").glob("rooms_gravity_*.pt"))) == 1
    assert len((tmp_path / "out" / "spherical" / "metrics.csv").read_text().splitlines()) == 2
    # then each detector's second phase, the spherical one's through random fields of view
    assert saved["fov_epochs"] == 1 and saved["fov_share"] == 0.5
    assert saved["drop_hidden"] is True  # the decoding rule, which `usf-graph targets` shows
    for name in ("spherical", "planar"):
        assert len((tmp_path / "out" / name / "second_phase" / "metrics.csv").read_text()
                   .splitlines()) == 2
    for name in ("spherical", "planar"):
        for k in PROTOCOL:
            r = dict(saved[name][k])
            # the spherical detector's up estimate, scored against each view's gravity
            up = r.pop("up", None)
            assert (up is None) == (name == "planar")
            if up is not None:
                assert up["views"] == 2 and 0 <= up["gross_unsure"] <= min(up["gross"], up["unsure"]) <= 2
            assert set(r) == {"AP", "AP50", "AP50_every_box", "AP75", "AR50", "usf_mAP@10",
                              "usf_mAP@50"}
            if k in ("a", "b"):  # the panoramas cut no box: both rules agree
                assert r["AP50_every_box"] == r["AP50"]
            assert all(-1 <= v <= 1 for v in r.values())
        assert (tmp_path / "out" / f"{name}.pt").is_file()
    assert (tmp_path / "out" / "det_results.png").is_file()
    assert "| spherical |" in format_table(res) and "(c) fisheye 190" in format_table(res)
    # resuming the finished run loads every stage and scores the same detectors again
    again = run(root=tmp_path / "rooms", out=tmp_path / "out", size=32, num_train=3, num_test=2,
                epochs=1, batch_size=2, progress=False, up_train=4, up_epochs=1, up_extra=2,
                fov_epochs=1, channel_scale=0.5, resume=True)
    assert again["spherical"] == res["spherical"] and again["planar"] == res["planar"]
    assert not res["resumed"] and again["resumed"]  # its seconds: this invocation's only
    # the shell's command hands its options to run and prints these results' tables and
    # targets (run itself stands in: the shell has no --up-train, and it ran just above)
    calls = []
    monkeypatch.setattr("usf_graph.train.det.run",
                        functools.wraps(run)(lambda **kw: calls.append(kw) or again))
    capsys.readouterr()
    assert main(["train", "det", "--root", str(tmp_path / "rooms"), "--out", str(tmp_path / "out"),
                 "--size", "32", "--num-train", "3", "--num-test", "2", "--epochs", "1",
                 "--batch-size", "2", "--up-epochs", "1", "--up-extra", "2", "--fov-epochs", "1",
                 "--channel-scale", "0.5", "--no-planar", "--resume"]) == 0
    given = {"size": 32, "num_train": 3, "num_test": 2, "epochs": 1, "batch_size": 2,
             "up_epochs": 1, "up_extra": 2, "fov_epochs": 1, "channel_scale": 0.5,
             "planar": False, "resume": True}
    assert {k: calls[0][k] for k in given} == given
    out = capsys.readouterr().out
    assert "Detection on procedural rooms, trained on upright panoramas (3 views; 2 test" in out
    assert f"test views each; {again['seconds']} s since --resume)" in out
    for metric in ("AP50", "AP50_every_box", "AP", "usf_mAP@10"):
        assert f"{metric}:\n{format_table(res, metric)}" in out
    assert "The issue's targets (bold: misses):" in out and f"figure: {res['figure']}" in out
    monkeypatch.undo()
    # the zero-shot tests see fewer boxes than the panorama of the same views
    assert saved["boxes"]["c"] <= saved["boxes"]["a"] and saved["boxes"]["b"] == saved["boxes"]["a"]
    # and only they have boxes the camera cuts, which scoring ignores
    assert saved["ignored_boxes"]["a"] == saved["ignored_boxes"]["b"] == 0
    assert saved["ignored_boxes"]["d"] == int(DetectionSet.spherical(sets_d := protocol_sets(
        tmp_path / "rooms", size=32, num_train=0, num_test=2, progress=False)["d"]).ignored().sum())
    assert 0 < saved["ignored_boxes"]["d"] < len(sets_d.boxes)
    # eval det reads the checkpoints back (--known-up: each view's true gravity)
    for name in ("spherical", "planar"):
        capsys.readouterr()
        assert main(["eval", "det", str(tmp_path / "out" / f"{name}.pt"), "--root",
                     str(tmp_path / "rooms"), "--size", "32", "--num-test", "2", "--test", "a",
                     "b", "--known-up"]) == 0
        out = capsys.readouterr().out
        assert f"(a) {saved['boxes']['a']} true boxes, 0 of them ignored" in out
        # the estimate's report, as the protocol recorded it (the planar one has none)
        for k in ("a", "b"):
            if name == "planar":
                assert f"({k}) up estimate" not in out
            else:
                up = saved[name][k]["up"]
                assert (f"({k}) up estimate: median error {up['median_err_deg']:.1f} deg, "
                        f"{up['gross']} of 2 views") in out
    blob = torch.load(tmp_path / "out" / "spherical.pt", weights_only=True)
    net = SphericalDetector.from_config(blob["config"])
    net.load_state_dict(blob["state_dict"])
    data = DetectionSet.spherical(protocol_sets(tmp_path / "rooms", size=32, num_train=0,
                                                num_test=2, progress=False)["a"])
    z = torch.tensor([0.0, 0.0, 1.0])
    kw = dict(threshold=0.0, k=5, nms=None)
    got = predict(net, data, up=z, **kw)
    x, mask, *_ = data.collate([0, 1])
    with torch.no_grad():
        want = net.eval().decode(net(x, mask, up=z.expand(2, 3)), **kw)
    assert len(got) == 2 and all(len(g["boxes"]) == 5 for g in got)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g["boxes"], w["boxes"])
    # --up-lines: the estimate picks among each image's line axes, through every lens
    capsys.readouterr()
    assert main(["eval", "det", str(tmp_path / "out" / "spherical.pt"), "--root", str(tmp_path / "rooms"),
                 "--size", "32", "--num-test", "2", "--test", "c", "d", "--up-lines"]) == 0
    out = capsys.readouterr().out
    sets = protocol_sets(tmp_path / "rooms", size=32, num_train=0, num_test=2, progress=False)
    up, axes = lines_up(net.gravity, sets["d"])
    data_d = DetectionSet.spherical(sets["d"])
    r = score(predict(net, data_d, up=up), data_d, net.num_classes)
    assert f"(d) AP {100 * r['AP']:.2f}, AP50 {100 * r['AP50']:.2f}" in out
    n = int(torch.isfinite(axes).all(-1).all(-1).sum())
    n_c = int(torch.isfinite(lines_up(net.gravity, sets["c"])[1]).all(-1).all(-1).sum())
    said = {ln[:3]: ln for ln in out.splitlines() if " up estimate: " in ln}
    assert said["(d)"].endswith(f"picked among straight-line axes on {n} views")
    assert said["(c)"].endswith(f"picked among straight-line axes on {n_c} views")
    for name, flags, why in (("spherical", ["--test", "d", "--up-lines", "--known-up"], "exclude each other"),
                             ("planar", ["--test", "d", "--up-lines"], "--up-lines needs a spherical model"),
                             ("spherical", ["--render", "soft"], "--render is segmentation's"),
                             ("spherical", ["--test", "e"], "detection has tests a, b, c, d, not 'e'")):
        assert main(["eval", "det", str(tmp_path / "out" / f"{name}.pt"), *flags]) == 2
        assert why in capsys.readouterr().err


def test_detection_sets_batch_boxes_and_fields_of_view(tmp_path):
    sets = protocol_sets(tmp_path, size=32, num_train=0, num_test=2, progress=False)
    assert "train" not in sets
    sph = DetectionSet.spherical(sets["c"])
    x, mask, boxes, classes, image = sph.collate([1, 0])
    assert x.shape == (2, 10242, 3) and mask is not None and 0 < mask.float().mean() < 0.6
    n0, n1 = (int(sph.box_ptr[i + 1] - sph.box_ptr[i]) for i in (0, 1))
    assert image.tolist() == [0] * n1 + [1] * n0 and len(boxes) == len(classes) == n0 + n1
    pl = DetectionSet.planar(sets["c"], 64, 32)
    xp, mp, *_ = pl.collate([0])
    assert xp.shape == (1, 3, 32, 64) and mp.shape == (32, 64)
    # the re-imaged fisheye is black where the lens does not see
    assert float(xp[0][:, ~mp].abs().max()) == 0 and float(xp[0][:, mp].mean()) > 0.05
    assert DetectionSet.planar(sets["a"], 64, 32).mask is None
    head = sph.first(1)  # the first sample, its boxes and the shared mask
    assert len(head) == 1 and torch.equal(head.x, sph.x[:1]) and head.mask is sph.mask
    assert torch.equal(head.boxes, sph.boxes[:n0]) and head.box_ptr.tolist() == [0, n0]
    assert len(sph.first(5)) == 2
    # the share of each box the lens sees, and the boxes it cuts, ignored in scoring
    cam = sets["d"].camera
    pin = DetectionSet.spherical(sets["d"])
    share = share_in_view(sets["d"].boxes.numpy(), lambda d: cam.sees(d)[1])
    assert np.array_equal(pin.seen, share) and (share < FULLY_SEEN).any() and (share >= FULLY_SEEN).any()
    assert np.array_equal(DetectionSet.planar(sets["d"], 64, 32).seen, share)
    assert np.array_equal(np.concatenate([pin.ignored(0), pin.ignored(1)]), share < FULLY_SEEN)
    assert np.array_equal(pin.first(1).ignored(0), pin.ignored(0))
    # finding exactly the boxes the lens sees whole scores 1 with them ignored, less without
    found = [dict(zip(("boxes", "classes"), pin.truth(i)), scores=np.ones(len(pin.ignored(i))))
             for i in range(len(pin))]
    found = [{k: v[~pin.ignored(i)] for k, v in f.items()} for i, f in enumerate(found)]
    got = score(found, pin, len(DETECTION_CLASSES))
    assert got["AP50"] == pytest.approx(1.0) and got["AP50_every_box"] < 0.99
    whole = DetectionSet.spherical(sets["a"])
    assert whole.seen is None and not whole.ignored(0).any() and len(whole.ignored(0)) == int(whole.box_ptr[1])
    assert DetectionSet.planar(sets["a"], 64, 32).seen is None  # a panorama cuts no box
    mixed = SimpleNamespace(**{k: getattr(sets["c"], k) for k in ("x", "boxes", "box_class", "box_ptr")},
                            mask=sets["c"].mask.clone())
    mixed.mask[1, :5] = ~mixed.mask[1, :5]
    with pytest.raises(ValueError, match="different fields of view; a batch shares one mask"):
        DetectionSet.spherical(mixed)


def test_random_fields_of_view_cut_batches_and_their_boxes(tmp_path):
    sets = protocol_sets(tmp_path, size=32, num_train=0, num_test=4, progress=False)
    data, pos = DetectionSet.spherical(sets["a"]), sets["a"].grid.pos.double()
    assert data.mask is None and len(data.boxes) > 4
    every = ThroughRandomFields(data, pos, share=1.0, seed=3)
    again = ThroughRandomFields(data, pos, share=1.0, seed=3)
    x0, _, b0, c0, i0 = data.collate([0, 1, 2, 3])
    cuts = set()
    for _ in range(6):
        x, seen, boxes, classes, image = every([0, 1, 2, 3])
        assert torch.equal(x, x0) and seen.dtype == torch.bool and 0.05 < seen.float().mean() < 0.6
        # exactly the boxes whose centre's nearest grid point is seen, in order
        keep = seen[(box_centres(b0.double()) @ pos.T).argmax(1)]
        assert torch.equal(boxes, b0[keep]) and torch.equal(classes, c0[keep])
        assert torch.equal(image, i0[keep])
        assert torch.equal(seen, again([0, 1, 2, 3])[1])  # the seed fixes the draws
        cuts.add(int(seen.sum()))
    assert len(cuts) == 6  # a new field of view each batch
    never = ThroughRandomFields(data, pos, share=0.0)
    got = never([2, 0])
    assert got[1] is None and all(torch.equal(a, b) for a, b in zip(got[2:], data.collate([2, 0])[2:]))
    # a camera's own mask is kept: the cut is within it
    lens = DetectionSet.spherical(sets["d"])
    seen = ThroughRandomFields(lens, pos, share=1.0)([0])[1]
    assert not (seen & ~lens.mask).any()
    # through a given lens, turned about gravity: its field of view, and the boxes it shows
    gen = torch.Generator().manual_seed(4)
    torch.rand((), generator=gen)
    _, seen, boxes, _, _ = ThroughRandomFields(data, pos, 1.0, seed=4, camera=sets["d"].camera)([0, 1, 2, 3])
    assert torch.equal(seen, camera_field(sets["d"].camera, pos, "yaw", gen))
    assert torch.equal(boxes, b0[seen[(box_centres(b0.double()) @ pos.T).argmax(1)]])
    with pytest.raises(ValueError, match="share"):
        ThroughRandomFields(data, pos, share=1.5)
    with pytest.raises(ValueError, match="grid's points"):
        ThroughRandomFields(data, pos[:10])


def test_detection_step_with_an_up_estimate_joint_or_frozen(tmp_path):
    """A gravity detector reads the jittered known up; its up loss is added while the
    estimate trains, and once frozen the estimate is not run and adds nothing."""
    import torch

    from usf_graph.models import SphericalDetector
    from usf_graph.train.det import detection_step
    from usf_graph.train.gravity import UP_JITTER, up_loss

    sets = protocol_sets(tmp_path, size=32, num_train=0, num_test=2, progress=False)
    data = DetectionSet.spherical(sets["a"])
    batch = data.collate([0, 1])
    x, mask, boxes, classes, image = batch
    torch.manual_seed(0)
    m = SphericalDetector(num_classes=12, gravity=True).train()
    z = torch.tensor([[0.0, 0, 1]] * 2)
    for frozen in (False, True):
        m.gravity.requires_grad_(not frozen)
        calls = []
        hook = m.gravity.register_forward_hook(lambda *a, calls=calls: calls.append(1))
        torch.manual_seed(5)
        loss, stats, n = detection_step(m, batch)
        hook.remove()
        torch.manual_seed(5)
        out = m(x, mask, up=z + UP_JITTER * torch.randn(2, 3))
        want = m.loss(out, boxes, classes, image)[0]
        if not frozen:
            want = want + up_loss(m.gravity.head, out["gravity"], z, {})
        torch.testing.assert_close(loss, want)
        assert n == 2 and (calls == []) == frozen and ("up_err_deg" in stats) != frozen


class _Planted(__import__("usf_graph.models", fromlist=["PlanarDetector"]).PlanarDetector):
    """A planar detector whose box fields hold, at each true box's nearest output point,
    exactly what its loss trains them towards (and its size ``scale`` times), whatever the image."""

    def __init__(self, boxes, image, scale=1.0, aspect=1.0):
        super().__init__(num_classes=3, height=16, width=32, channels=(4, 8))
        self.boxes, self.image, self.scale, self.aspect = boxes, image, scale, aspect

    def forward(self, x, mask=None):
        import torch

        from usf_graph.models.centernet import box_centres

        out = super().forward(x, mask)
        W = self.out_camera.width
        near = (box_centres(self.boxes) @ self.points.T).argmax(1)
        uv = self._pixels(box_centres(self.boxes))
        off = torch.stack([uv[:, 0] - near % W, uv[:, 1] - near // W], -1)
        stretch = torch.tensor([self.aspect, 1 / self.aspect], dtype=self.boxes.dtype)
        t = torch.cat([off, (self.boxes[:, 2:4] * self.scale * stretch).log(), self.boxes[:, 4:5]], -1)
        box = out["box"].detach().double().clone()
        box[self.image, near] = t
        return {**out, "box": box}


def test_box_quality_decodes_each_true_box_at_its_own_centre_point():
    import math

    import torch

    from usf_graph.ops import box_area
    from usf_graph.train.det import box_quality

    deg = math.radians
    boxes = torch.tensor([[deg(10), deg(5), deg(30), deg(20), deg(10)],
                          [deg(-100), deg(-20), deg(25), deg(25), 0.0],
                          [deg(170), deg(30), deg(40), deg(20), deg(-30)]], dtype=torch.float64)
    image = torch.tensor([0, 0, 1])
    data = DetectionSet(torch.zeros(2, 16, 32, 3, dtype=torch.uint8), boxes,
                        torch.tensor([0, 2, 1]), torch.tensor([0, 2, 3]))
    q = box_quality(_Planted(boxes, image), data, progress=False)
    # perfect fields: the decoded boxes are the true ones
    np.testing.assert_allclose(q["iou"], 1.0, atol=1e-6)
    np.testing.assert_allclose(q["centre_deg"], 0.0, atol=1e-5)
    np.testing.assert_allclose(q["log_size_err"], 0.0, atol=1e-6)  # float32 boxes
    # boxes 1.2 times too large on both axes: the size error is log 1.2, the aspect's none,
    # and on its true centre the box holds the true one: the IoU is the ratio of their areas
    q = box_quality(_Planted(boxes, image, scale=1.2), data, progress=False)
    np.testing.assert_allclose(q["log_size_err"], math.log(1.2), atol=1e-6)
    np.testing.assert_allclose(q["log_aspect_err"], 0.0, atol=1e-6)
    big = boxes.clone()
    big[:, 2:4] *= 1.2
    np.testing.assert_allclose(q["iou_true_centre"], (box_area(boxes) / box_area(big)).numpy(), atol=1e-6)
    assert (q["iou"] < q["iou_true_centre"] + 1e-6).all()
    # 1.3 times wider and 1.3 times lower (none of the boxes is taller than wide): the
    # aspect is log 1.3 off, the size not at all
    q = box_quality(_Planted(boxes, image, aspect=1.3), data, progress=False)
    np.testing.assert_allclose(q["log_aspect_err"], math.log(1.3), atol=1e-6)
    np.testing.assert_allclose(q["log_size_err"], 0.0, atol=1e-6)
    # a set without a true box: nothing to measure
    empty = DetectionSet(data.x, boxes[:0], torch.tensor([], dtype=torch.long), torch.tensor([0, 0, 0]))
    assert all(v.shape == (0,) for v in box_quality(_Planted(boxes[:0], image[:0]), empty,
                                                      progress=False).values())


@pytest.mark.parametrize("task", ["det", "seg"])
def test_a_bad_channel_scale_stops_a_protocol_before_it_renders(tmp_path, task):
    import importlib

    module = importlib.import_module(f"usf_graph.train.{task}")
    for kw, said in ((dict(channel_scale=-0.5), "channel scale must be in"),
                     (dict(fov_share=-0.1), "random fields of view must be in")):
        with pytest.raises(ValueError, match=said):
            module.run(root=tmp_path / "rooms", out=tmp_path / "out", progress=False, **kw)
    assert not (tmp_path / "rooms").exists() and not (tmp_path / "out").exists()


def test_score_names_each_iou_threshold_by_its_value():
    """One true box and one detection that overlaps it by an IoU of 0.12: found at USF's
    IoU 0.10, missed at 0.50 and by COCO's thresholds (0.50 and up)."""
    import math

    from usf_graph.ops import box_iou

    true = torch.tensor([[0.0, 0.0, math.radians(30), math.radians(30), 0.0]], dtype=torch.float64)
    found = true.clone()
    found[0, 0] = math.radians(23.2)
    assert 0.105 < float(box_iou(found, true)) < 0.15
    data = DetectionSet(torch.zeros(1, 16, 32, 3, dtype=torch.uint8), true, torch.tensor([1]),
                        torch.tensor([0, 1]))
    got = score([{"boxes": found.numpy(), "classes": np.array([1]), "scores": np.array([0.9])}], data, 3)
    assert got["usf_mAP@10"] == 1.0 and got["usf_mAP@50"] == 0.0
    assert got["AP50"] == got["AP50_every_box"] == got["AP"] == 0.0
