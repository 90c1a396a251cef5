"""SphericalConv vs Conv2d (same pixel count): the static-graph path (one bound graph,
x [B, N, C]), the general PyG path (a batch of B graphs as [B N, C], geometry computed in
the call; the layer keeps the last graph's plan), the same with a new graph each call,
UprightConv (oriented kernels in up's frame) in both forms, the naive per-edge PyG path,
per-edge MLP weights and, when installed, torch-harmonics DISCO. Times in one run; reports
ratios.

    python benchmarks/conv.py [--level 6] [--batch 8] [--channels 64] [--threads 2]

torch-harmonics is optional and benchmark-only: `pip install --no-deps torch-harmonics==0.9.3`.
"""

from __future__ import annotations

import argparse
import math

import torch
from timing import best_time, in_form

from usf_graph import grids
from usf_graph.frontend import grid_graph
from usf_graph.nn import SphericalConv, UprightConv, geodesic_radius_graph

DEVICE = torch.device("cpu")


def timeit(fn, reps: int) -> float:
    return best_time(fn, reps, DEVICE)


def fwd_bwd(f, x):
    def run():
        x.grad = None
        f(x).sum().backward()
    return run


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--level", type=int, default=6)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--channels", type=int, default=64)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--device", default="cpu", help="cpu or cuda (times include a synchronize)")
    p.add_argument("--skip-slow", action="store_true", help="skip naive and mlp variants")
    p.add_argument("--scaling", action="store_true",
                   help="only the scaling run: icosahedral levels 4..8 (2.5k..655k points)")
    p.add_argument("--locality", action="store_true",
                   help="scaling run with the points sorted along HEALPix's nested (Z-order) "
                        "curve, to measure what memory locality is worth")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    if a.scaling:
        return scaling(a)
    global DEVICE
    DEVICE = dev = torch.device(a.device)
    g = grids.icosahedral(a.level)
    N, B, C = len(g), a.batch, a.channels
    r = 1.6 * g.spacing
    ei, ew = grid_graph(g, r)  # the cached geodesic radius graph
    ei, ew, area, pos = ei.to(dev), ew.float().to(dev), g.area.float().to(dev), g.pos.to(dev)
    where = torch.cuda.get_device_name(dev) if dev.type == "cuda" else f"{a.threads} threads"
    print(f"N={N} points, {ei.shape[1] / N:.1f} neighbours/point, B={B}, {C}->{C} ch, "
          f"K=4, {where}")
    x = torch.randn(B, N, C, requires_grad=True, device=dev)
    conv = SphericalConv(C, C, r, num_basis=4).to(dev)
    side = int(math.sqrt(N))
    img = torch.randn(B, C, side, N // side + 1, requires_grad=True, device=dev)
    c2d = torch.nn.Conv2d(C, C, 3, padding=1).to(dev)
    rows = {}
    rows["Conv2d 3x3"] = (timeit(lambda: c2d(img), a.reps), timeit(fwd_bwd(c2d, img), a.reps))
    conv.bind(ei, ew, node_weight=area)
    rows["SphericalConv (static, bound)"] = (timeit(lambda: conv(x), a.reps),
                                             timeit(fwd_bwd(conv, x), a.reps))
    # oriented kernels in the frame of a per-sample up: 3K sparse products instead of K
    up = torch.nn.functional.normalize(torch.randn(B, 3, device=dev), dim=-1)
    uconv = UprightConv(C, C, r, num_basis=4).to(dev).bind(ei, ew, node_weight=area, pos=pos)
    fu = lambda x: uconv(x, up)  # noqa: E731
    rows["UprightConv (static, bound)"] = (timeit(lambda: fu(x), a.reps),
                                           timeit(fwd_bwd(fu, x), a.reps))
    # the form the device does not take by default, for the side-by-side (aggregate.WIDE)
    other = "wide" if dev.type == "cpu" else "blockwise"
    name = "one product per call" if other == "wide" else "blockwise"
    for k, f in ((f"SphericalConv (static, {name})", conv), (f"UprightConv (static, {name})", fu)):
        f = in_form(other, f)
        rows[k] = (timeit(lambda f=f: f(x), a.reps), timeit(fwd_bwd(f, x), a.reps))
    # the same B samples as a PyG batch of B graphs: [B N, C], edges offset per graph
    eib = torch.cat([ei + b * N for b in range(B)], 1)
    ewb, areab = ew.repeat(B), area.repeat(B)
    xg = x.detach().reshape(B * N, C).requires_grad_(True)
    g = lambda x: conv(x, eib, ewb, node_weight=areab)  # noqa: E731
    rows[f"SphericalConv (general, PyG batch of {B})"] = (timeit(lambda: g(xg), a.reps),
                                                          timeit(fwd_bwd(g, xg), a.reps))
    batch = torch.arange(B, device=dev).repeat_interleave(N)
    posb = pos.repeat(B, 1)
    gu = lambda x: uconv(x, up, eib, ewb, node_weight=areab, pos=posb, batch=batch)  # noqa: E731
    rows[f"UprightConv (general, PyG batch of {B})"] = (timeit(lambda: gu(xg), 1),
                                                        timeit(fwd_bwd(gu, xg), 1))
    # the same call when every batch is another graph: the plan built anew each time
    for k, f, layer in (("SphericalConv", g, conv), ("UprightConv", gu, uconv)):
        f = new_graph_each_call(f, layer)
        rows[f"{k} (general, a new graph each call)"] = (timeit(lambda f=f: f(xg), 1),
                                                         timeit(fwd_bwd(f, xg), 1))
    try:
        from torch_harmonics import DiscreteContinuousConvS2

        nlat = round(math.sqrt(N / 2))  # an equiangular grid with about N nodes (143x286 at level 6)
        nlon = 2 * nlat
        disco = disco_conv(DiscreteContinuousConvS2, C, (nlat, nlon), 4, r).to(dev)
        print(f"DISCO: {nlat}x{nlon} equiangular, {disco.kernel_size} isotropic piecewise-linear "
              f"basis functions, theta_cutoff = {disco.theta_cutoff:.4f} (ours {r:.4f})")
        xi = torch.randn(B, C, nlat, nlon, requires_grad=True, device=dev)
        rows[f"DISCO (torch-harmonics, {nlat}x{nlon})"] = (timeit(lambda: disco(xi), a.reps),
                                                    timeit(fwd_bwd(disco, xi), a.reps))
    except Exception as e:  # noqa: BLE001 - optional competitor
        print(f"(torch-harmonics DISCO skipped: {type(e).__name__}: {e})")
    if not a.skip_slow:
        naive = lambda x: conv(x, ei, ew, node_weight=area, fast=False)  # noqa: E731
        rows["naive PyG per-edge"] = (timeit(lambda: naive(x), 1), timeit(fwd_bwd(naive, x), 1))
        mlp = SphericalConv(C, C, r, kernel="mlp", hidden=8).to(dev)
        fm = lambda x: mlp(x[:1], ei, ew, node_weight=area)  # noqa: E731
        t = (timeit(lambda: fm(x), 1) * B, timeit(fwd_bwd(fm, x), 1) * B)
        rows["per-edge MLP weights (B=1 x B)"] = t
    base = rows["Conv2d 3x3"]
    print("\n| variant | fwd (ms) | fwd+bwd (ms) | fwd / Conv2d | fwd+bwd / Conv2d |")
    print("|---|---|---|---|---|")
    for k, (t1, t2) in rows.items():
        print(f"| {k} | {1e3 * t1:.3g} | {1e3 * t2:.3g} | {t1 / base[0]:.2f} | {t2 / base[1]:.2f} |")
    ours = rows["SphericalConv (static, bound)"]
    gen = rows[f"SphericalConv (general, PyG batch of {B})"]
    print(f"\ngeneral / static: fwd {gen[0] / ours[0]:.2f}x, fwd+bwd {gen[1] / ours[1]:.2f}x")
    up_s, up_g = rows["UprightConv (static, bound)"], rows[f"UprightConv (general, PyG batch of {B})"]
    print(f"UprightConv / SphericalConv (static): fwd {up_s[0] / ours[0]:.2f}x, fwd+bwd "
          f"{up_s[1] / ours[1]:.2f}x; UprightConv general / static: fwd {up_g[0] / up_s[0]:.2f}x, "
          f"fwd+bwd {up_g[1] / up_s[1]:.2f}x")
    disco = next((v for k, v in rows.items() if k.startswith("DISCO")), None)
    if disco is not None:
        print(f"\nDISCO / SphericalConv: fwd {disco[0] / ours[0]:.2f}x, "
              f"fwd+bwd {disco[1] / ours[1]:.2f}x")


def new_graph_each_call(f, layer):
    """``f`` with ``layer``'s kept PyG-form plan dropped before each call, as when every
    batch is another graph (point clouds; the general rows reuse it: the same grid)."""
    def run(x):
        layer._plans.clear()
        return f(x)
    return run


def disco_conv(cls, C, shape, K, radius):
    """torch-harmonics DISCO with the same kernel as ours: K isotropic basis functions (its
    kernel_shape=(n,) gives about n/2 of them) and the same support radius."""
    for n in range(K, 4 * K):
        d = cls(C, C, shape, shape, kernel_shape=(n,), basis_type="piecewise linear",
                grid_in="equiangular", grid_out="equiangular", theta_cutoff=radius)
        if d.kernel_size == K:
            return d
    raise RuntimeError(f"no kernel_shape gives {K} isotropic basis functions")


def scaling(a, B: int = 2, C: int = 32):
    """Time per point of the fast SphericalConv from 2.5k to 655k points, next to Conv2d
    3x3 on an image with the same pixel count (the same memory hierarchy effects)."""
    print(f"scaling: B={B}, {C}->{C} channels, K=4, radius 1.6 spacings, {a.threads} threads"
          + (", points in HEALPix nested order" if a.locality else ""))
    print("| level | points | fwd (ms) | fwd+bwd (ms) | fwd+bwd (ns/point/ch) "
          "| Conv2d fwd+bwd (ns/pixel/ch) | fwd+bwd / Conv2d |")
    print("|---|---|---|---|---|---|---|")
    for level in range(4, 9):
        g = grids.icosahedral(level)
        pos, area = g.pos, g.area.float()
        if a.locality:  # same points, numbered so that neighbours sit close in memory
            order = grids.locality_order(pos)
            pos, area = pos[order], area[order]
        r = 1.6 * g.spacing
        ei, ew = geodesic_radius_graph(pos, r)
        conv = SphericalConv(C, C, r, num_basis=4).bind(ei, ew.float(), node_weight=area)
        x = torch.randn(B, len(g), C, requires_grad=True)
        f = conv
        reps = a.reps if level < 8 else 1
        t1, t2 = timeit(lambda f=f, x=x: f(x), reps), timeit(fwd_bwd(f, x), reps)
        side = int(math.sqrt(len(g)))
        img = torch.randn(B, C, side, len(g) // side + 1, requires_grad=True)
        tc = timeit(fwd_bwd(torch.nn.Conv2d(C, C, 3, padding=1), img), reps)
        n = B * len(g) * C
        print(f"| {level} | {len(g)} | {1e3 * t1:.1f} | {1e3 * t2:.1f} | {1e9 * t2 / n:.1f} "
              f"| {1e9 * tc / n:.1f} | {t2 / tc:.2f} |", flush=True)


if __name__ == "__main__":
    main()
