import cv2
import numpy as np
import torch

from usf_graph import SphericalFrontend, cameras, grids
from usf_graph.cli import main


def test_lift_cli_writes_sample_and_preview(tmp_path, capsys):
    cam = cameras.KannalaBrandt(60.0, 60.0, 79.5, 59.5, 160, 120, k=(0.01, 0, 0, 0))
    cam.save(tmp_path / "cam.yaml")
    rng = np.random.default_rng(0)
    img = (rng.random((120, 160, 3)) * 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "img.png"), img[..., ::-1])  # cv2 writes BGR
    rc = main(["lift", str(tmp_path / "img.png"), "--camera", str(tmp_path / "cam.yaml"),
               "--grid", "icosahedral:4", "--out", str(tmp_path / "s.pt"),
               "--preview", str(tmp_path / "s.png")])
    assert rc == 0
    out = capsys.readouterr()
    assert "points visible" in out.out and "building lift table" in out.err
    d = torch.load(tmp_path / "s.pt", weights_only=True)
    ref = SphericalFrontend(cameras.load(tmp_path / "cam.yaml"), grids.icosahedral(4)).lift(img)
    assert torch.equal(d["x"], ref) and d["x"].shape == (2562, 3)
    assert d["mask"].sum() == (ref.abs().sum(1) > 0).sum() > 100
    assert (tmp_path / "s.png").stat().st_size > 10_000


def test_lift_cli_reports_bad_input(tmp_path, capsys):
    cam = cameras.Pinhole(100.0, 100.0, 79.5, 59.5, 160, 120)
    cam.save(tmp_path / "cam.yaml")
    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((60, 80), np.uint8))
    rc = main(["lift", str(tmp_path / "small.png"), "--camera", str(tmp_path / "cam.yaml"),
               "--grid", "icosahedral:3"])
    assert rc == 2
    assert "160" in capsys.readouterr().err
    assert main(["lift", str(tmp_path / "none.png"), "--camera", str(tmp_path / "cam.yaml")]) == 2


def test_info_reports_versions_and_working_extensions(capsys):
    assert main(["info"]) == 0
    out = capsys.readouterr().out
    assert torch.__version__ in out
    assert "compiled extensions  load and run" in out
    assert "USF_GRAPH_CACHE" in out and f"torch threads        {torch.get_num_threads()}" in out


def test_camera_cli_prints_field_of_view_and_plots(tmp_path, capsys):
    path = "tests/fixtures/ros_equidistant.yaml"
    cam = cameras.load(path)
    assert main(["camera", path, "--plot", str(tmp_path / "lnm.png")]) == 0
    out = capsys.readouterr().out
    assert "KannalaBrandt" in out
    assert f"{cam.solid_angle():.4f} sr" in out and f"{cam.fov_deg:.2f} deg" in out
    assert (tmp_path / "lnm.png").stat().st_size > 20_000
    # a 180 degree equidistant fisheye, written in our own format, covers half the sphere
    cameras.Fisheye(150, 255.5, 255.5, 512, 512, fov_deg=180).save(tmp_path / "half.yaml")
    assert main(["camera", str(tmp_path / "half.yaml")]) == 0
    assert "of the sphere" in (line := capsys.readouterr().out.splitlines()[3])
    assert abs(float(line.split("=")[1].split("%")[0]) - 50.0) < 0.6


def test_camera_cli_reports_bad_files(tmp_path, capsys):
    (tmp_path / "bad.yaml").write_text("usf_graph_camera: 1\nmodel: Fancy\nparams: {}\n")
    assert main(["camera", str(tmp_path / "bad.yaml")]) == 2
    assert "Fancy" in capsys.readouterr().err
    (tmp_path / "odd.yaml").write_text("focal: 3\n")
    assert main(["camera", str(tmp_path / "odd.yaml")]) == 2
    assert "unrecognized calibration format" in capsys.readouterr().err
    assert main(["camera", str(tmp_path / "missing.yaml")]) == 2
