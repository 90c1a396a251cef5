"""Time one frame of ``usf-graph predict`` (a camera's image in, labels or boxes out) next
to a planar network's forward pass on the same image at the same number of pixels.

    python benchmarks/predict_frame.py [--lens fisheye|pinhole|panorama] [--size 512]
                                       [--task seg det] [--threads 2] [--reps 5]
                                       [--channel-scale 1.0] [--device cpu|cuda] [--modes]

What a robot pays per frame. Spherical: the protocols' DeepLab (seg) and detector (det),
untrained (the cost does not depend on the weights), through
:func:`~usf_graph.train.apply.segment_image` / :func:`~usf_graph.train.apply.detect_image`
on a ``size x size`` image of the protocols' 190-degree fisheye or 90-degree pinhole (a
``2 size x size`` panorama): lifting onto icosahedral:5 (the camera's tables built once,
before timing, as ``predict`` builds them once for a camera's frames), the up estimate or
a given up (an IMU), the network, and the answer in the camera's terms (labels in its
pixels; boxes decoded with NMS). Each stage is also timed alone. Planar: the
:class:`PlanarDeepLab` (seg) or :class:`PlanarDetector` (det) with the spherical model's
channels, forward only, on the image resized (``cv2.INTER_AREA``, counted) to about as many
pixels as the grid has points; nothing after the forward pass is counted for it, so the
ratio favours it. For seg, the spherical and planar U-Nets' forward passes (up given) are
timed too, the pair whose training step ``seg_step.py`` compares. ``--modes`` also times
the spherical network (up given) under ``torch.inference_mode``, autocast (bfloat16 on the
CPU, float16 on a GPU) and ``torch.compile`` (its compilation not counted), and for seg the
soft labels (:meth:`SphericalFrontend.to_labels`), each beside the plain run.
"""

from __future__ import annotations

import argparse
import math

import cv2
import numpy as np
import torch
from timing import best_time

from usf_graph.models import (
    PlanarDeepLab,
    PlanarDetector,
    PlanarUNet,
    SphericalDeepLabV3,
    SphericalDetector,
    SphericalUNet,
)
from usf_graph.scenes.lenses import protocol_cameras
from usf_graph.train import apply, defaults, scaled_channels
from usf_graph.train.det import make_detector
from usf_graph.train.seg import make_model

LENSES = {"fisheye": "fisheye190", "pinhole": "pinhole90", "panorama": "equirectangular"}


def channels(cls, scale: float) -> dict:
    """``cls``'s channel arguments as the protocols build it at ``scale``."""
    c = {**defaults(cls), **scaled_channels(cls, scale)}
    return {k: c[k] for k in ("channels", "aspp_channels") if k in c}


def models(task: str, scale: float):
    """The spherical protocol model of ``task`` and its planar competitor's class and kwargs
    (the spherical model's channels)."""
    if task == "seg":
        return make_model("spherical_deeplab", channel_scale=scale), PlanarDeepLab, \
            channels(SphericalDeepLabV3, scale)
    sph = make_detector(channel_scale=scale)
    return sph, PlanarDetector, {"num_classes": sph.num_classes, **channels(SphericalDetector, scale)}


def planar_shape(points: int, aspect: int) -> tuple[int, int]:
    """``(H, W)``, multiples of 16 with ``W = aspect H`` and ``H W`` about ``points``."""
    h = max(16, 16 * round(math.sqrt(points / aspect) / 16))
    return h, aspect * h


@torch.no_grad()
def stages(task: str, net, image: np.ndarray, cam, reps: int, dev: torch.device,
           modes: bool = False) -> dict:
    """Seconds per frame, whole and by stage, for the spherical model (on ``dev``); with
    ``modes``, its network in PyTorch's other modes too."""
    up = np.array([0.0, 0.0, 1.0])
    run = apply.segment_image if task == "seg" else apply.detect_image
    run(net, image, cam)  # builds the camera's tables, as a first frame does
    fe, x, mask = apply.lift_for(net, image, cam)
    u = torch.as_tensor(up, dtype=x.dtype, device=x.device)[None]
    out = net(x, mask, up=u)
    finish = (lambda: fe.to_image(out[0].argmax(-1).to(torch.uint8).cpu(), mode="nearest")) \
        if task == "seg" else (lambda: net.decode(out, k=100, threshold=0.05, nms=0.5))
    t = {"frame, its up estimate": best_time(lambda: run(net, image, cam), reps, dev),
         "frame, up given (IMU)": best_time(lambda: run(net, image, cam, up=up), reps, dev),
         "lift": best_time(lambda: apply.lift_for(net, image, cam), reps, dev),
         "up estimate": best_time(lambda: net.gravity(x, mask), reps, dev),
         "network, up given": best_time(lambda: net(x, mask, up=u), reps, dev),
         "answer in the camera's terms": best_time(finish, reps, dev)}
    if modes:
        t.update(other_modes(net, x, mask, u, reps, dev))
        if task == "seg":
            probs = out[0].softmax(-1).cpu()
            t["answer, soft labels"] = best_time(lambda: fe.to_labels(probs, "soft"), reps, dev)
    return t


def other_modes(net, x, mask, u, reps: int, dev: torch.device) -> dict:
    """The network (up given) under inference mode, autocast and ``torch.compile``."""
    low = torch.bfloat16 if dev.type == "cpu" else torch.float16

    def inference():
        with torch.inference_mode():
            return net(x, mask, up=u)

    def autocast():
        with torch.autocast(dev.type, dtype=low):
            return net(x, mask, up=u)

    compiled = torch.compile(net)
    compiled(x, mask, up=u)  # compiles once, as a deployed model would before its frames
    return {"network, inference_mode": best_time(inference, reps, dev),
            f"network, autocast {str(low).split('.')[-1]}": best_time(autocast, reps, dev),
            "network, torch.compile": best_time(lambda: compiled(x, mask, up=u), reps, dev)}


@torch.no_grad()
def planar_forward(net, image: np.ndarray, h: int, w: int):
    """A planar network on ``image`` resized to ``h x w`` (on the network's device)."""
    small = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
    dev = next(net.parameters()).device
    return net(torch.from_numpy(small).to(dev).permute(2, 0, 1)[None].float() / 255)


def time_task(task: str, image: np.ndarray, cam, reps: int, scale: float,
              dev: torch.device, modes: bool = False) -> dict:
    """Seconds per frame of ``task``'s spherical model by stage, and of its planar competitors."""
    net, planar_cls, kw = models(task, scale)
    net.to(dev).eval()
    h, w = planar_shape(net.num_points, 2 if cam.width == 2 * cam.height else 1)
    planar = planar_cls(**kw, **({"height": h, "width": w} if task == "det" else {})).to(dev).eval()
    print(f"\n{task}: {type(net).__name__} on icosahedral:5 ({net.num_points} points) / "
          f"{planar_cls.__name__} on {w}x{h} ({w * h} pixels)")
    t = stages(task, net, image, cam, reps, dev, modes)
    t["planar forward"] = best_time(lambda: planar_forward(planar, image, h, w), reps, dev)
    if task == "seg":
        unet = make_model("spherical_unet", channel_scale=scale).to(dev).eval()
        _, x, mask = apply.lift_for(unet, image, cam)
        up = torch.tensor([[0.0, 0.0, 1.0]], device=dev)
        t["spherical U-Net network, up given"] = best_time(
            torch.no_grad(lambda: unet(x, mask, up=up)), reps, dev)
        punet = PlanarUNet(**channels(SphericalUNet, scale)).to(dev).eval()
        t["planar U-Net forward"] = best_time(lambda: planar_forward(punet, image, h, w), reps, dev)
    return t


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--lens", default="fisheye", choices=list(LENSES))
    p.add_argument("--size", type=int, default=512, help="image height in pixels")
    p.add_argument("--task", nargs="+", default=["seg", "det"], choices=["seg", "det"])
    p.add_argument("--threads", type=int, default=2, help="CPU threads")
    p.add_argument("--reps", type=int, default=5)
    p.add_argument("--channel-scale", type=float, default=1.0,
                   help="the models' channels times this (the 15-minute recipes: 0.5)")
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    p.add_argument("--modes", action="store_true", help="also inference mode, autocast, "
                   "torch.compile and soft labels (compiling takes a minute)")
    a = p.parse_args(argv)
    dev = torch.device(a.device)
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    cam = protocol_cameras(a.size)[LENSES[a.lens]]
    image = (np.random.default_rng(0).random((cam.height, cam.width, 3)) * 255).astype(np.uint8)
    where = torch.cuda.get_device_name(dev) if dev.type == "cuda" else f"CPU, {a.threads} threads"
    print(f"{a.lens} {cam.width}x{cam.height}, {where}, best of {a.reps} frames, "
          f"channel scale {a.channel_scale}")
    res = {}
    for task in a.task:
        res[task] = t = time_task(task, image, cam, a.reps, a.channel_scale, dev, a.modes)
        print("| stage | ms | frames/s |\n|---|---|---|")
        for k, v in t.items():
            print(f"| {k} | {1e3 * v:.1f} | {1 / v:.1f} |")
        print(f"spherical frame (its estimate) / planar forward: "
              f"{t['frame, its up estimate'] / t['planar forward']:.2f}x; up given: "
              f"{t['frame, up given (IMU)'] / t['planar forward']:.2f}x")
    return res


if __name__ == "__main__":
    main()
