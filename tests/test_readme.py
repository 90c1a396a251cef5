"""The README's quick tour (every code block of the section) runs as printed, on a smaller
grid to keep the suite fast."""

import re
from pathlib import Path

import cv2
import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]


def test_quick_tour_runs(monkeypatch):
    text = (ROOT / "README.md").read_text()
    section = text.split("## Quick tour", 1)[1].split("\n## ", 1)[0]
    code = "\n".join(re.findall(r"```python\n(.*?)```", section, re.S))  # every block, in order
    assert "grids.icosahedral(6)" in code
    monkeypatch.chdir(ROOT)  # the tour loads a calibration from tests/fixtures
    ns = {}
    exec(compile(code.replace("grids.icosahedral(6)", "grids.icosahedral(4)"), "README", "exec"), ns)
    N = 10 * 4 ** 4 + 2
    assert ns["xb"].shape == (2, N, 3) and ns["y"].shape == (N, 16)
    assert ns["inv"].shape == (2, N, 16) and ns["y_coarse"].shape == (len(ns["coarse"]), 16)
    assert ns["rot"].x.shape == ns["img"].x.shape and bool(ns["valid"].all())
    assert ns["yb"].shape == (2, N, 16) and ns["g_feat"].shape == (2, 16)
    assert ns["err"] < 1e-10
    data, why = ns["data"], ns["why"]  # the explainer credits only the edges into point 0
    assert torch.equal(why.edge_mask > 0, data.edge_index[1] == 0)


def test_your_camera_section_runs_python_and_shell(tmp_path, monkeypatch):
    import shlex

    import torch

    from usf_graph.cli import main
    from usf_graph.frontend import load_lifted

    text = (ROOT / "README.md").read_text()
    section = text.split("## Your camera", 1)[1].split("\n## ", 1)[0]
    code = "\n".join(re.findall(r"```python\n(.*?)```", section, re.S))
    (tmp_path / "tests").symlink_to(ROOT / "tests")  # the section reads tests/fixtures
    monkeypatch.chdir(tmp_path)
    ns = {}
    exec(compile(code.replace("grids.icosahedral(6)", "grids.icosahedral(3)"), "README", "exec"), ns)
    assert ns["both"].mask.all() and ns["img"].mask.sum() > 300
    assert type(ns["mei"]).__name__ == "Mei" and ns["mei"].image_mask is not None
    assert ns["h"].shape == (int(ns["img"].mask.sum()), 8)
    shell = re.findall(r"```bash\n(.*?)```", section, re.S)
    lines = [ln for block in shell for ln in block.splitlines() if ln.startswith("usf-graph ")]
    assert len(lines) == 16
    for ln in lines:
        argv = shlex.split(ln.split("#")[0].replace("icosahedral:6", "icosahedral:3"))[1:]
        assert main(argv) == 0, ln
    assert load_lifted("sample.pt").x.shape == (642, 3)
    rig = load_lifted("rig.pt")
    assert rig.mask.all() and torch.isfinite(rig.x).all()
    assert (tmp_path / "fisheye.png").stat().st_size > 10_000
    # the leveling: up from the askew room's lines, and the command turning it level
    assert np.degrees(np.arccos(ns["up"] @ ns["tilt"][2])) < 1.0  # gravity, in the askew frame
    assert (tmp_path / "level.png").exists() and (tmp_path / "level_fisheye.png").exists()
    assert cv2.imread(str(tmp_path / "stitched.png")).shape == (512, 1024, 3)  # the rig, stitched
    assert cv2.imread(str(tmp_path / "cube.png")).shape == (768, 1024, 3)  # a dice cube map
    assert b"GPano" in (tmp_path / "pano_again.jpg").read_bytes()  # and back: a 360 photo
    video = cv2.VideoCapture(str(tmp_path / "stitched.mp4"))  # and its video, frame by frame
    assert video.get(cv2.CAP_PROP_FRAME_COUNT) == 8 and video.get(cv2.CAP_PROP_FPS) == 10
    ok, frame = video.read()
    video.release()
    assert ok and frame.shape == (512, 1024, 3)
    leveled = cv2.VideoCapture(str(tmp_path / "level.mp4"))  # every frame leveled by its lines
    assert leveled.get(cv2.CAP_PROP_FRAME_COUNT) == 8
    leveled.release()
    clip = ns["clip"]  # the same video lifted, frame by frame, onto one sphere each
    assert len(clip) == 8 and clip[0].mask.all() and clip[7].frame.item() == 7
    assert (clip[0].x - clip[1].x).abs().mean() > 0.01  # the world turned between frames


def test_scenes_section_runs(tmp_path, monkeypatch):
    """The scenes section's code, with the datasets shrunk to 2 rooms on a small grid, and
    its command."""
    from usf_graph.cli import main

    text = (ROOT / "README.md").read_text()
    section = text.split("## Indoor scenes through any lens", 1)[1].split("\n## ", 1)[0]
    code = "\n".join(re.findall(r"```python\n(.*?)```", section, re.S))
    code = code.replace('grid="icosahedral:5"', 'grid="icosahedral:2", num_scenes=2')
    code = code.replace('rotate="so3")', 'rotate="so3", num_scenes=2, grid="icosahedral:2")')
    code = code.replace('camera=protocol_cameras(256)["fisheye190"])',
                        'camera=protocol_cameras(64)["fisheye190"], num_scenes=2, grid="icosahedral:2")')
    code = code.replace('RoomsDetection("data/rooms", "train")',
                        'RoomsDetection("data/rooms", "train", grid="icosahedral:2", num_scenes=2)')
    assert code.count("num_scenes=2") == 4
    monkeypatch.chdir(tmp_path)
    ns = {}
    exec(compile(code, "README", "exec"), ns)
    assert ns["view"].rgb.shape == (256, 512, 3) and len(ns["view"].boxes) > 3
    assert ns["tilted"].label.shape == (256, 512)
    assert len(ns["det"]) == 2 and ns["det"][0].boxes.shape[1] == 5
    assert (ns["fisheye"].y[ns["fisheye"].mask] == ns["test_rot"].y[ns["fisheye"].mask]).all()
    cmd = re.findall(r"```bash\n(.*?)```", section, re.S)[0].split("#")[0].split()
    assert cmd[0].endswith("usf-graph") and main([*cmd[1:], "--num", "1", "--size", "64"]) == 0
    assert (tmp_path / "runs/scenes/contact_sheet.png").exists()


def test_detection_section_runs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    text = (ROOT / "README.md").read_text()
    section = text.split("## Detection with spherical boxes", 1)[1].split("\n## ", 1)[0]
    code = "\n".join(re.findall(r"```python\n(.*?)```", section, re.S))
    scope = {}
    exec(compile(code, "README detection", "exec"), scope)  # noqa: S102 - our own README
    b = scope["found"][0]["boxes"]
    assert 1 <= len(b) <= 5 and b.shape[1] == 5 and len(scope["found"]) == 2
    assert "--dataset pandora" in section and "not run here" in section


def test_segmentation_section_runs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    text = (ROOT / "README.md").read_text()
    section = text.split("## Semantic segmentation on the sphere", 1)[1].split("\n## ", 1)[0]
    code = "\n".join(re.findall(r"```python\n(.*?)```", section, re.S))
    scope = {}
    exec(compile(code, "README segmentation", "exec"), scope)  # noqa: S102 - our own README
    assert tuple(scope["logits"].shape) == (2, 10242, 13)
    assert tuple(scope["pixels"].shape) == (128, 256) and int(scope["pixels"].max()) < 13
    assert "--fold all" in section and "not run here" in section


def test_predict_section_runs_on_the_your_camera_files(tmp_path, monkeypatch):
    """The predict section's commands as printed, on the fisheye files that the "Your
    camera" commands write, with small untrained models saved where the checkpoints of
    ``make demo-seg`` and ``make demo-det`` would be."""
    import json
    import shlex

    import cv2
    import torch

    from usf_graph import cameras
    from usf_graph.cli import main
    from usf_graph.frontend import render
    from usf_graph.models import SphericalDeepLabV3, SphericalDetector
    from usf_graph.train import save_checkpoint
    from usf_graph.viz import labelled_panorama

    text = (ROOT / "README.md").read_text()
    setup = [ln for block in re.findall(r"```bash\n(.*?)```", text.split("## Your camera", 1)[1]
                                        .split("\n## ", 1)[0], re.S)
             for ln in block.splitlines() if ln.startswith("usf-graph ")][:2]
    section = text.split("## Your own images: `usf-graph predict`", 1)[1].split("\n## ", 1)[0]
    lines = [ln for block in re.findall(r"```bash\n(.*?)```", section, re.S)
             for ln in block.splitlines() if ln.startswith("usf-graph ")]
    assert [ln.split()[2] for ln in lines] == ["seg", "det", "seg", "seg"]
    (tmp_path / "tests").symlink_to(ROOT / "tests")
    monkeypatch.chdir(tmp_path)
    for ln in setup:  # fisheye.yaml, and pano.png re-imaged as fisheye.png
        if " render " in ln:
            cv2.imwrite("pano.png", (255 * labelled_panorama(512, 256)[..., ::-1]).astype("uint8"))
        assert main(shlex.split(ln)[1:]) == 0, ln
    pano = labelled_panorama(512, 256)
    for name, cam in zip(("front", "back"), cameras.load_rig("tests/fixtures/kalibr_rig.yaml").values()):
        view = render(pano, cameras.Equirectangular(512, 256), cam.with_fov(190))
        cv2.imwrite(f"{name}.png", (255 * view[..., ::-1]).astype("uint8"))  # as the section's Python
    torch.manual_seed(0)
    seg = SphericalDeepLabV3(level=3, channels=(8, 8, 8), aspp_channels=8, low_channels=8,
                             gravity=True)
    det = SphericalDetector(12, input_level=3, head_level=2, min_level=1, channels=(8, 8, 8),
                            gravity=True)
    Path("runs/seg_15min").mkdir(parents=True)
    Path("runs/det_15min").mkdir(parents=True)
    save_checkpoint("runs/seg_15min/spherical_deeplab.pt", seg,
                    {"model": "spherical_deeplab", "size": 96, **seg.config}, {})
    save_checkpoint("runs/det_15min/spherical.pt", det, det.config, {})
    # the robot's recording: front.png and back.png as a bag with an IMU (up: cam0's -y)
    import numpy as np
    import yaml

    from tests.test_bags import ROS2, image_msg, imu_msg, write_bag

    chain = yaml.safe_load(Path("tests/fixtures/kalibr_rig.yaml").read_text())
    chain["cam0"]["T_cam_imu"] = np.eye(4).tolist()
    Path("camchain-imucam.yaml").write_text(yaml.safe_dump(chain))
    msgs = [(chain[c]["rostopic"], image_msg(ROS2, cv2.imread(f"{n}.png")[..., ::-1], 1, 0), k)
            for k, (c, n) in enumerate((("cam0", "front"), ("cam1", "back")))]
    msgs += [("/imu0", imu_msg(ROS2, (0.0, -9.81, 0.0), 1, k * 10**7), 2 + k) for k in range(3)]
    write_bag(Path("drive"), False, msgs)
    for ln in lines:
        assert main(shlex.split(ln)[1:]) == 0, ln
    assert Path("predictions/drive_cam1_000000_labels.png").stat().st_size > 0
    assert Path("drive.mp4").stat().st_size > 1000
    assert Path("predictions/fisheye_labels.png").stat().st_size > 0
    assert Path("predictions/front_labels.png").stat().st_size > 0
    assert Path("predictions/back_seg.png").stat().st_size > 0
    assert Path("predictions/fisheye_seg.png").stat().st_size > 0
    doc = json.loads(Path("predictions/fisheye_boxes.json").read_text())
    assert doc["up"]["source"] == "given" and doc["interpolation"] == "area"


def test_deploying_section_runs_its_onnxruntime_code(tmp_path, monkeypatch):
    """The section's onnxruntime snippet runs as printed on a program exported for the
    README's fisheye (a small model, the check skipped: tests/train/test_export.py has it)."""
    import pytest
    import torch

    pytest.importorskip("onnxruntime")
    from usf_graph import cameras
    from usf_graph.models import SphericalUNet
    from usf_graph.train.export import export_model

    text = (ROOT / "README.md").read_text()
    section = text.split("## Deploying: `usf-graph export`", 1)[1].split("\n## ", 1)[0]
    code = "\n".join(re.findall(r"```python\n(.*?)```", section, re.S))
    cam = cameras.load(ROOT / "tests/fixtures/opencv_sample_fisheye.yaml", fov_deg=190)
    torch.manual_seed(0)
    model = SphericalUNet(13, level=3, channels=(4, 4), gravity=True, pairs=0).eval()
    monkeypatch.chdir(tmp_path)
    export_model(model, cam, "deploy/fisheye_seg.onnx", up="input", check=False)
    ns = {}
    exec(compile(code, "README", "exec"), ns)
    assert ns["labels"].shape == (960, 1280) and ns["labels"].dtype.name == "uint8"
    assert (ns["labels"] == 255).any() and ns["up_read"].tolist() == [0.0, 0.0, 1.0]


def test_markdown_links_resolve():
    """Every relative link of the README, docs/, benchmarks/README.md and the changelog
    names a file that exists and, with a #fragment, a heading of it (GitHub's anchors)."""
    def anchors(path):
        heads = re.findall(r"^#+\s+(.*)$", path.read_text(), re.M)
        return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in heads}

    pages = [ROOT / "README.md", ROOT / "CHANGELOG.md", ROOT / "benchmarks" / "README.md",
             *sorted((ROOT / "docs").glob("*.md"))]
    broken = []
    for page in pages:
        for link in re.findall(r"\]\(([^)\s]+)\)", page.read_text()):
            if link.startswith(("http://", "https://", "mailto:")):
                continue
            path, _, frag = link.partition("#")
            target = (page.parent / path) if path else page
            if not target.exists() or (frag and target.suffix == ".md" and frag not in anchors(target)):
                broken.append(f"{page.relative_to(ROOT)}: {link}")
    assert not broken, broken
    assert len(pages) > 5
