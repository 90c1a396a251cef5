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


def cmd_info(args) -> int:
    import numpy
    import torch

    from . import __version__
    from .frontend.cache import default_cache_dir

    rows = [("usf-graph", __version__), ("python", platform.python_version()),
            ("torch", torch.__version__), ("numpy", numpy.__version__)]
    for mod in (*REQUIRED, *OPTIONAL):
        try:
            rows.append((mod, getattr(__import__(mod), "__version__", "ok")))
        except Exception as e:  # noqa: BLE001 - report, do not crash
            rows.append((mod, "not installed (optional, for usf-graph export: pip install "
                              "'usf-graph[export]')" if mod in OPTIONAL and isinstance(e, ImportError)
                         else f"NOT AVAILABLE ({type(e).__name__}: {e})"))
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


def cmd_cache(args) -> int:
    from .frontend.cache import GEOMETRY_VERSION, default_cache_dir

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
        for f in files:
            f.unlink(missing_ok=True)
        print(f"removed {len(files)} files; geometry is rebuilt on next use")
    return 0
