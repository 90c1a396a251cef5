"""The README's examples run, and what they print holds."""

import json

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
    # the errors are the angles to +z of what the estimate returns
    err = ex.up_errors(lambda x, m: {"up": torch.tensor([[0.0, 1.0, 0.0]]).expand(len(x), 3)},
                       type("DS", (), {"x": torch.zeros(3, 5, 3), "mask": torch.ones(3, 5, dtype=torch.bool)}))
    assert err.shape == (3,) and abs(err - 90).max() < 1e-4
