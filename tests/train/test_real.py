"""The real datasets' commands on their fixtures: training, the checkpoint's record of its
data, and ``eval`` on that data."""

import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from tests.datasets.test_stanford import NAMES, _write_pano
from usf_graph.cli import main
from usf_graph.train.checkpoints import load_protocol_model

FIXTURE = Path(__file__).parents[1] / "fixtures" / "pandora"


def test_stanford_command_on_fixtures(tmp_path, capsys):
    root = tmp_path / "s2d3ds"
    root.mkdir()
    (root / "semantic_labels.json").write_text(json.dumps(NAMES))
    for area, stem in (("1", "a"), ("2", "b"), ("3", "c"), ("4", "d"), ("6", "e"), ("5a", "f"),
                       ("5b", "g")):
        _write_pano(root, area, stem, W=64, H=32, seed=len(stem) + ord(stem))
    assert main(["train", "seg", "--dataset", "stanford2d3ds", "--root", str(root), "--out",
                 str(tmp_path / "out"), "--size", "16", "--epochs", "1", "--batch-size", "2",
                 "--gray"]) == 0  # for a mono camera: the checkpoint says so
    res = json.loads((tmp_path / "out" / "results.json").read_text())
    r = res["spherical_unet"]["fold1"]
    assert res["gray"] is True
    assert set(r) >= {"mIoU", "mAcc", "sphere_mIoU", "per_image_mIoU"}
    assert np.isfinite(r["mIoU"]) and res["spherical_unet"]["mean"]["mIoU"] == r["mIoU"]
    ckpt = str(tmp_path / "out" / "fold1_spherical_unet.pt")
    # eval scores a Stanford checkpoint on its own fold's test areas, as train did
    capsys.readouterr()
    assert main(["eval", "seg", ckpt, "--root", str(root)]) == 0
    line = next(ln for ln in capsys.readouterr().out.splitlines() if "mIoU" in ln)
    assert line.startswith("fold 1 test: ") or line.startswith("fold 1 test ")
    assert f"mIoU {100 * r['mIoU']:.2f}," in line and f"mAcc {100 * r['mAcc']:.2f}" in line
    stored = sorted(p.name for p in (root / "processed").glob("stanford_*.pt"))
    assert stored == ["stanford_f1_test_icosahedral5_16.pt", "stanford_f1_train_icosahedral5_16.pt"]
    assert load_protocol_model(ckpt).dataset == "stanford2d3ds" and load_protocol_model(ckpt).fold == 1
    assert load_protocol_model(ckpt).model.gray and load_protocol_model(ckpt).model.gravity.gray
    assert main(["eval", "seg", ckpt, "--root", str(root), "--gray"]) == 0  # gray already: the same
    assert f"mIoU {100 * r['mIoU']:.2f}," in capsys.readouterr().out
    assert main(["eval", "seg", ckpt, "--root", str(root), "--known-up"]) == 0  # +z, as released
    assert "fold 1 test up estimate" in capsys.readouterr().out
    for argv, match in ((["--test", "a"], "rooms options"), (["--dataset", "pandora"], "not seg data"),
                        (["--dataset", "rooms", "--fold", "2"], "--fold")):
        assert main(["eval", "seg", ckpt, "--root", str(root), *argv]) == 2
        assert re.search(match, capsys.readouterr().err), match


def test_pandora_command_on_the_fixture(tmp_path, capsys):
    root = tmp_path / "pandora"
    shutil.copytree(FIXTURE, root)
    assert main(["train", "det", "--dataset", "pandora", "--root", str(root), "--out",
                 str(tmp_path / "out"), "--epochs", "1", "--batch-size", "2"]) == 0
    res = json.loads((tmp_path / "out" / "results.json").read_text())
    assert set(res["spherical"]) >= {"AP", "AP50", "usf_mAP@10"}
    assert np.isfinite(res["spherical"]["AP50"])
    # the upright detector, its up estimate trained first on the same panoramas (no mask)
    blob = torch.load(tmp_path / "out" / "spherical.pt", weights_only=True)
    cfg = blob["config"]
    assert cfg["upright"] and cfg["gravity"] and blob["data"] == {"dataset": "pandora"}
    assert len((tmp_path / "out" / "up_estimate" / "metrics.csv").read_text().splitlines()) == 25
    # eval scores it on PANDORA's test split, as train did, also when saved before
    # checkpoints named their data (told by its 47 classes)
    from usf_graph.models import SphericalDetector
    from usf_graph.train.engine import save_checkpoint

    del blob["data"]
    torch.save(blob, tmp_path / "old.pt")
    for ckpt in (tmp_path / "out" / "spherical.pt", tmp_path / "old.pt"):
        capsys.readouterr()
        assert main(["eval", "det", str(ckpt), "--root", str(root)]) == 0
        line = next(ln for ln in capsys.readouterr().out.splitlines() if "AP50" in ln)
        assert line.startswith("pandora test ") and f"AP50 {100 * res['spherical']['AP50']:.2f}," in line
    rooms = SphericalDetector(num_classes=12)
    save_checkpoint(tmp_path / "rooms.pt", rooms, rooms.config, {})
    for argv, match in (([str(tmp_path / "rooms.pt"), "--dataset", "pandora"],
                         "predicts 12 classes .* pandora has 47"),
                        ([str(ckpt), "--size", "64"], "--size: rooms options")):
        assert main(["eval", "det", *argv, "--root", str(root)]) == 2
        assert re.search(match, capsys.readouterr().err), match


def _woodscape(root):
    from tests.datasets.test_woodscape import _calibration, _write

    for name, yaw in (("00001_FV", 0), ("00002_RV", 180), ("00004_FV", 0), ("00003_MVL", 90),
                      ("00005_MVR", -90)):
        _write(root, name, _calibration(yaw))
    (root / "train.txt").write_text("00001_FV.png\n00002_RV.png\n00004_FV.png\n")
    (root / "val.txt").write_text("00003_MVL.png\n00005_MVR.png\n")
    return root


class _Fixed(torch.nn.Module):
    """The same per-point logits ``[N, C]`` for every image."""

    def __init__(self, logits):
        super().__init__()
        self.logits, self.w = logits, torch.nn.Parameter(torch.zeros(()))
        self.config = {"num_classes": logits.shape[1]}

    def forward(self, x, mask, up=None):
        return self.logits.expand(len(x), -1, -1)


class _Constant(torch.nn.Module):
    """Predicts class ``c`` everywhere, and checks that every batch shares one field of
    view, the one each of its samples was lifted with."""

    def __init__(self, ds, c):
        super().__init__()
        self.ds, self.c, self.w = ds, c, torch.nn.Parameter(torch.zeros(()))
        self.config = {"num_classes": 10}

    def forward(self, x, mask, up=None):
        for row in x:
            i = next(i for i in range(len(self.ds)) if torch.equal(self.ds.x[i].float(), row))
            assert torch.equal(self.ds.mask[i], torch.ones_like(self.ds.mask[i]) if mask is None else mask)
        assert up is not None and torch.equal(up, torch.tensor([[0.0, 0.0, 1.0]] * len(x)))
        out = torch.zeros(*x.shape[:2], 10)
        out[..., self.c] = 1
        return out


def test_woodscape_scores_each_image_on_its_own_pixels(tmp_path):
    """A model that says "road" everywhere, scored by hand from the label PNGs: road's IoU
    is the road pixels' share of the pixels with a ray, every other class 0."""
    from usf_graph.datasets import WoodScape
    from usf_graph.datasets.woodscape import CLASSES
    from usf_graph.frontend.interpolation import valid_pixels
    from usf_graph.train.real import evaluate_fields
    from usf_graph.train.seg_metrics import confusion_matrix, scores

    root = _woodscape(tmp_path / "ws")
    mvr = root / "semantic_annotations" / "gtLabels" / "00005_MVR.png"
    label = cv2.imread(str(mvr), 0)
    label[-30:] = 6  # less road than the left camera's mirror image: the cameras score apart
    cv2.imwrite(str(mvr), label)
    ds = WoodScape(root, "val", grid="icosahedral:3", scale=0.5, progress=False)
    r = evaluate_fields(_Constant(ds, 1), ds, batch_size=2, progress=False,  # known up: the default
                        names=CLASSES)
    truth, cams = [], {}
    for i, name in enumerate(ds.names):
        label = cv2.imread(str(root / "semantic_annotations" / "gtLabels" / f"{name}.png"), 0)
        label = cv2.resize(np.where(label < 10, label, 0).astype(np.uint8), (64, 48),
                           interpolation=cv2.INTER_NEAREST)
        t = label[valid_pixels(ds.frontend(i).camera)]
        truth.append(t)
        cams[ds.camera_names[i]] = (t == 1).mean() / len(set(t.tolist()) | {1})
    t = np.concatenate(truth)
    present = set(t.tolist()) | {1}
    assert r["IoU"]["road"] == pytest.approx((t == 1).mean(), abs=1e-12)
    assert r["mIoU"] == pytest.approx((t == 1).mean() / len(present), abs=1e-12)
    assert r["mAcc"] == pytest.approx(1 / len(set(t.tolist())), abs=1e-12)
    assert r["cameras"] == pytest.approx(cams, abs=1e-12) and list(r["cameras"]) == ["MVL", "MVR"]
    assert abs(cams["MVL"] - cams["MVR"]) > 0.01
    y, area = ds.y.numpy(), ds.grid.area.numpy()
    seen = y != 255
    road = (area * ((y == 1) & seen)).sum() / (area * seen).sum()
    assert r["sphere_mIoU"] == pytest.approx(road / len(set(y[seen].tolist()) | {1}), rel=1e-9)
    soft = evaluate_fields(_Constant(ds, 1), ds, batch_size=2, progress=False, names=CLASSES,
                           render="soft")  # each point's class probabilities blended
    assert soft["IoU"] == r["IoU"] and soft["cameras"] == r["cameras"]
    # logits of very different scales: blending them, not the probabilities, labels otherwise
    logits = torch.full((len(ds.grid), 10), -30.0)
    logits[:, 1] = 0.0
    logits[:, 6] = torch.randn(len(ds.grid), generator=torch.Generator().manual_seed(0)) * 8
    got = evaluate_fields(_Fixed(logits), ds, batch_size=2, progress=False, render="soft")
    confs = [confusion_matrix(ds.frontend(i).to_labels(logits.softmax(-1), "soft").numpy(),
                              ds.label_image(i), 10) for i in range(len(ds))]
    want = scores(sum(confs), [str(c) for c in range(10)])
    assert got["IoU"] == pytest.approx(want["IoU"], abs=1e-12) and got["IoU"]["6"] > 0
    from usf_graph.models import PlanarUNet

    with pytest.raises(ValueError, match="evaluate_fields scores spherical models; a planar one has no grid"):
        evaluate_fields(PlanarUNet(10, channels=(4, 4)), ds, progress=False)


def test_woodscape_command_trains_on_four_cameras_and_eval_scores_it_again(tmp_path, capsys):
    root = _woodscape(tmp_path / "ws")
    out = tmp_path / "out"
    assert main(["train", "seg", "--dataset", "woodscape", "--root", str(root), "--out", str(out),
                 "--models", "spherical_unet", "--epochs", "1", "--batch-size", "2",
                 "--up-epochs", "2"]) == 0  # the up estimate first, alone, by field of view too
    printed = capsys.readouterr().out
    res = json.loads((out / "results.json").read_text())
    assert res["samples"] == {"train": 3, "test": 2} and res["fields_of_view"] == 2
    assert res["up_epochs"] == 2 and len((out / "up_estimate" / "metrics.csv").read_text().splitlines()) == 3
    r = res["spherical_unet"]
    assert np.isfinite(r["mIoU"]) and set(r["cameras"]) == {"MVL", "MVR"}
    assert f"mIoU {100 * r['mIoU']:.2f}," in printed
    ckpt = load_protocol_model(out / "spherical_unet.pt")
    assert (ckpt.dataset, ckpt.scale, ckpt.model.config["num_classes"]) == ("woodscape", 0.5, 10)
    # eval reads the vehicle frame's up with --known-up, as training scored it
    assert main(["eval", "seg", str(out / "spherical_unet.pt"), "--root", str(root), "--known-up"]) == 0
    said = capsys.readouterr().out
    for m in ("mIoU", "mAcc", "sphere_mIoU", "per_image_mIoU"):  # each score, in percent
        assert f" {m} {100 * r[m]:.2f}" in said and f"spherical_unet: mIoU {100 * r['mIoU']:.2f}," in said
    assert ("spherical_unet per camera: mIoU " + ", ".join(f"{c} {100 * v:.2f}" for c, v in
                                                          r["cameras"].items())) in said
    for argv, match in ((["train", "seg", "--dataset", "woodscape", "--models", "planar_unet"],
                         "spherical models .* not \\['planar_unet'\\]"),
                        (["train", "seg", "--scale", "0.5"], "--scale resizes WoodScape"),
                        (["train", "det", "--dataset", "woodscape"], "segmentation dataset"),
                        (["eval", "seg", str(out / "spherical_unet.pt"), "--dataset", "stanford2d3ds"],
                         "predicts 10 classes")):
        assert main([*argv, "--root", str(root), "--out", str(tmp_path / "x")]
                    if argv[0] == "train" else [*argv, "--root", str(root)]) == 2
        assert re.search(match, capsys.readouterr().err), match
