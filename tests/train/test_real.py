"""The real datasets' commands on their fixtures: training, the checkpoint's record of its
data, and ``eval`` on that data."""

import json
import re
import shutil
from pathlib import Path

import numpy as np
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
