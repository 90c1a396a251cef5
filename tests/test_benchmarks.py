"""The benchmark scripts still run (tiny sizes; what they time is not asserted here)."""

import contextlib
import io
import os
import re
import runpy
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


def run(script, *args):
    """``python script args`` run in this process as ``__main__`` (a fresh interpreter
    spent 6 s of each run importing torch and PyG), its printout returned. What the
    scripts set for themselves (threads, seeds, environment) is put back afterwards."""
    saved = (torch.get_num_threads(), cv2.getNumThreads(), torch.get_rng_state(),
             np.random.get_state(), dict(os.environ), list(sys.path), sys.argv, os.getcwd())
    out = io.StringIO()
    try:
        os.chdir(ROOT)
        sys.argv = [str(ROOT / script), *args]
        sys.path.insert(0, str((ROOT / script).parent))  # their shared `timing`
        with contextlib.redirect_stdout(out):
            try:
                runpy.run_path(str(ROOT / script), run_name="__main__")
            except SystemExit as e:
                assert e.code in (None, 0), f"{script} exited with {e.code}:\n{out.getvalue()[-2000:]}"
    finally:
        threads, cv_threads, rng, np_rng, env, path, sys.argv, cwd = saved
        torch.set_num_threads(threads)
        cv2.setNumThreads(cv_threads)
        torch.set_rng_state(rng)
        np.random.set_state(np_rng)
        os.environ.clear()
        os.environ.update(env)
        sys.path[:] = path
        os.chdir(cwd)
    return out.getvalue()


def test_conv_and_lift_benchmarks_run():
    out = run("benchmarks/conv.py", "--level", "2", "--batch", "1", "--channels", "4",
              "--reps", "1", "--skip-slow")
    assert "| SphericalConv (static, bound) |" in out and "| Conv2d 3x3 |" in out
    assert "| SphericalConv (general, PyG batch of 1) |" in out and "general / static" in out
    out = run("benchmarks/lift.py", "--level", "2", "--reps", "1")
    assert out.count("| panorama 2048x1024 |") == 2 and out.count("| fisheye 1280x960") == 2


def test_equivariance_benchmark_runs():
    """The distance-only network's rotation error stays near the lift's own interpolation
    error; a Conv2d on the panorama's is many times it."""
    out = run("benchmarks/equivariance.py", "--grids", "icosahedral:3", "--widths", "64")
    ratios = {row.split("|")[3].strip(): float(row.split("|")[-2]) for row in out.splitlines()
              if row.startswith("| icosahedral:3") or row.startswith("| equirectangular")}
    assert ratios["gaussian K=3, r=4 spacings"] < 3 < 10 < ratios["Conv2d 3x3"], ratios


def test_train_step_benchmark_runs():
    out = run("benchmarks/train_step.py", "--batch", "2", "--reps", "1")
    assert "| SphericalClassifier | 10242 |" in out and "spherical / planar step time" in out


def test_scenes_benchmark_runs():
    out = run("benchmarks/scenes.py", "--rooms", "1", "--sizes", "32")
    assert "| equirectangular 64x32 |" in out and "| pinhole90 512x512 |" in out


def test_boxes_benchmark_runs():
    out = run("benchmarks/boxes.py", "--pairs", "300", "--k", "30")
    assert "| batched float32 (fast path) |" in out and "| sampling, 200k points |" in out
    assert "NMS over 30 candidates (float64; best of 5; same IoUs: True)" in out
    assert "| NMS, 10% live |" in out and "| NMS, 100% live |" in out


def test_sparse_indices_benchmark_runs():
    out = run("benchmarks/sparse_indices.py", "--reps", "1", "--batch", "1",
              "--channel-scale", "0.25", "--size", "64", "--tasks", "seg")
    for label in ("one sparse product", "DeepLab network", "DeepLab training step, batch 1"):
        assert f"| {label}" in out
    assert out.count("x |") == 3 and "detector" not in out


def test_seg_step_benchmark_runs():
    out = run("benchmarks/seg_step.py", "--batch", "1", "--level", "3", "--reps", "1",
              "--channel-scale", "0.5")  # both at half the channels: the planar U-Net's 257,357
    assert "channels [16, 32, 64, 64]" in out and "| PlanarUNet (32x16) | 512 | 257357 |" in out
    assert "| SphericalUNet (icosahedral:3) | 642 |" in out and "spherical / planar step time" in out
    out = run("benchmarks/seg_step.py", "--batch", "1", "--level", "3", "--reps", "1",
              "--model", "spherical_deeplab")
    assert "| SphericalDeepLabV3 (icosahedral:3) | 642 |" in out


def test_det_step_benchmark_runs():
    out = run("benchmarks/det_step.py", "--batch", "2", "--size", "32", "--reps", "1",
              "--channel-scale", "0.25", "--boxes", "2")
    assert "| PlanarDetector (64x32) | 2048 |" in out and "2 boxes per view" in out
    assert "| SphericalDetector (icosahedral:5) | 10242 |" in out and "spherical / planar step time" in out


def test_profile_step_benchmark_runs():
    out = run("benchmarks/profile_step.py", "--batch", "1", "--level", "3", "--steps", "1",
              "--rows", "5")
    assert "Self CPU time total" in out and "aten::" in out
    assert out.count("\n") < 40  # --rows bounds the table


def test_predict_frame_benchmark_runs():
    out = run("benchmarks/predict_frame.py", "--size", "64", "--reps", "1", "--channel-scale",
              "0.25", "--lens", "pinhole")
    assert "seg: SphericalDeepLabV3 on icosahedral:5 (10242 points) / PlanarDeepLab on 96x96" in out
    assert "det: SphericalDetector on icosahedral:5" in out and out.count("| frame, up given (IMU) |") == 2
    assert "| spherical U-Net network, up given |" in out and out.count("planar forward:") == 2


@pytest.mark.slow
def test_predict_frame_benchmark_times_the_other_modes():
    out = run("benchmarks/predict_frame.py", "--size", "64", "--reps", "1", "--channel-scale",
              "0.25", "--task", "seg", "--modes")
    for row in ("network, inference_mode", "network, autocast bfloat16", "network, torch.compile",
                "answer, soft labels"):
        assert f"| {row} |" in out, row


@pytest.mark.slow  # two exports of a protocol's level-5 model: about 40 s each task
@pytest.mark.parametrize("task", ["seg", "det"])
def test_export_frame_benchmark_runs(task):
    pytest.importorskip("onnxruntime")
    out = run("benchmarks/export_frame.py", "--task", task, "--size", "32", "--channel-scale", "0.25",
              "--reps", "1")
    assert "| ONNX in onnxruntime, up given |" in out and f"| {task}.pt2 |" in out
    if task == "seg":
        assert out.count("| 100.00% |") == 2  # both files agree with usf-graph
    else:  # every detection of both files found alike
        alike = re.findall(r"\| (\d+) of (\d+) \|", out)
        assert len(alike) == 2 and all(a == b and int(a) > 0 for a, b in alike)


@pytest.mark.slow  # two worker processes start and import torch: about 30 s
def test_render_split_benchmark_runs_and_checks_the_splits_agree():
    out = run("benchmarks/render_split.py", "--views", "3", "--workers", "1,2")
    rows = re.findall(r"^\| (segmentation 192x96|detection 256x128) \| [\d.]+ \| [\d.]+ \| [\d.]+x \|$",
                      out, re.M)
    assert rows == ["segmentation 192x96", "detection 256x128"]  # it exits when they differ


def test_lines_benchmark_runs():
    out = run("benchmarks/lines.py", "--sizes", "256", "--reps", "1")
    assert "| 256x128 |" in out and "first version (s)" in out


def test_reimage_benchmark_runs():
    out = run("benchmarks/reimage.py", "--sizes", "128", "--reps", "1")
    assert "| panorama 128x64 leveled |" in out and "| dual fisheye 2x64x64 -> panorama 128x64 |" in out
    diffs = re.findall(r"\| (\d+) \(([\d.]+)%\) \|", out)
    assert len(diffs) == 2 and all(int(d) <= 1 for d, _ in diffs)  # the two paths agree


def test_cubemap_benchmark_runs():
    out = run("benchmarks/cubemap.py", "--sizes", "64", "--reps", "1")
    assert "| panorama -> cube map 64x32 |" in out and "| cube map -> panorama 64x32 |" in out


def test_eac_benchmark_runs():
    out = run("benchmarks/eac.py", "--sizes", "64", "--reps", "1")
    assert "| panorama -> EAC 64x32 |" in out and "| EAC -> panorama 64x32 |" in out
