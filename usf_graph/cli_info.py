"""``usf-graph info`` and ``usf-graph cache``: what this installation has (versions, the
compiled extensions, the optional export packages, threads) and what its geometry cache
holds."""

from __future__ import annotations

import os
import platform

#: Imported by usf-graph: a failure to import one is a broken installation.
REQUIRED = ("torch_geometric", "torch_scatter", "torch_cluster", "scipy", "cv2", "healpy")
#: What ``usf-graph export`` needs (the ``export`` extra): absent is a choice, not a fault.
OPTIONAL = ("onnx", "onnxscript", "onnxruntime")


def checkpoint_rows(path) -> list[tuple[str, str]]:
    """What a checkpoint holds, as (field, value) rows for people: the model and its input,
    what it was trained on, the scores saved with it and what made it."""
    from .train import load_checkpoint
    from .train.checkpoints import model_name
    from .train.provenance import describe

    blob = load_checkpoint(path)
    cfg, data = blob["config"], blob.get("data", {})
    level = cfg.get("input_level", cfg.get("level"))
    name = model_name(blob) or "a model of unknown kind"
    numbers = sum(v.numel() for v in blob["state_dict"].values() if hasattr(v, "numel"))
    seen = (f"icosahedral:{level} ({10 * 4 ** level + 2} points)" if level is not None else
            f"{2 * cfg['size']}x{cfg['size']} panoramas" if "size" in cfg else
            f"{cfg['width']}x{cfg['height']} panoramas" if "height" in cfg else "images")
    flags = [k for k in ("gravity", "upright", "gray") if cfg.get(k)]
    rows = [("checkpoint", str(path)), ("model", f"{name}, {numbers:,} stored numbers"),
            ("input", seen + (f"; {', '.join(flags)}" if flags else "")),
            ("classes", str(cfg.get("num_classes", "?")))]
    if data:
        rows.append(("trained on", ", ".join(f"{k} {v}" for k, v in data.items())))
    for test, m in sorted(blob.get("metrics", {}).items()):  # seg and det: per test; mnist: NR, R
        shown = [f"{k} {100 * m[k]:.2f}" for k in ("mIoU", "AP50") if k in m] \
            if isinstance(m, dict) else [f"accuracy {100 * m:.2f}"] if isinstance(m, float) else []
        if shown:
            rows.append((f"({test})", ", ".join(shown)))
    rows.append(("made by", describe(blob.get("provenance"))))
    return rows


def cmd_info(args) -> int:
    if getattr(args, "checkpoint", None):
        rows = checkpoint_rows(args.checkpoint)
        w = max(len(k) for k, _ in rows)
        for k, v in rows:
            print(f"{k:<{w}}  {v}")
        return 0
    import numpy
    import torch

    from . import __version__
    from .frontend.cache import default_cache_dir

    rows = [("usf-graph", __version__), ("python", platform.python_version()),
            ("torch", torch.__version__), ("numpy", numpy.__version__)]
    ok = True  # every required package imports and the compiled extensions run
    for mod in (*REQUIRED, *OPTIONAL):
        try:
            rows.append((mod, getattr(__import__(mod), "__version__", "ok")))
        except Exception as e:  # noqa: BLE001 - report, do not crash
            ok = ok and mod in OPTIONAL
            rows.append((mod, "not installed (optional, for usf-graph export: pip install "
                              "'usf-graph[export]')" if mod in OPTIONAL and isinstance(e, ImportError)
                         else f"NOT AVAILABLE ({type(e).__name__}: {e})"))
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


def cmd_cache(args) -> int:
    from .frontend.cache import GEOMETRY_VERSION, GeometryCache, default_cache_dir

    d = default_cache_dir()
    if d is None:
        print("the disk cache is off (USF_GRAPH_CACHE=off); geometry is cached in memory only")
        return 0
    files = sorted(d.glob("*.npz")) if d.exists() else []
    print(f"cache directory  {d} (set USF_GRAPH_CACHE to move it, 'off' to disable)")
    print(f"geometry version {GEOMETRY_VERSION}")
    kinds: dict[str, list[int]] = {}
    for f in files:
        kinds.setdefault(f.name.split("-")[0], []).append(f.stat().st_size)
    for k, sizes in sorted(kinds.items()):
        print(f"  {k:<8} {len(sizes):5d} files {sum(sizes) / 1e6:10.2f} MB")
    total = sum(sum(v) for v in kinds.values())
    print(f"  {'total':<8} {len(files):5d} files {total / 1e6:10.2f} MB")
    if args.clear:
        GeometryCache(d).clear(disk=True)
        print(f"removed {len(files)} files; geometry is rebuilt on next use")
    return 0
