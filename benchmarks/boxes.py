"""Spherical box IoU: the batched exact IoU in float64 (reference) and float32 (fast path),
its float32 error on random overlapping pairs, and the time per pair against a per-pair
loop of the same code (how published spherical IoU code runs) and a sampling estimate.
Then a detector's NMS over its ``--k`` best candidates (float64, as decoding runs): the
IoU of every pair, as an exported program computes it, against the pairs whose bounding
caps meet; greedy NMS over every row against the live rows only.

    python benchmarks/boxes.py [--pairs 100000] [--k 100] [--threads 2]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch
from timing import best_time

from usf_graph.grids import fibonacci
from usf_graph.ops import box_iou, iou, nms_keep, pairwise_box_iou, points_in_boxes


def random_pairs(n, seed=0):
    rng = np.random.default_rng(seed)
    a = np.stack([rng.uniform(-math.pi, math.pi, n), np.arcsin(rng.uniform(-1, 1, n)),
                  rng.uniform(0.05, 2.0, n), rng.uniform(0.05, 2.0, n),
                  rng.uniform(-math.pi / 2, math.pi / 2, n)], -1)
    b = a.copy()
    b[:, :2] += rng.normal(0, 0.3, (n, 2))
    b[:, 1] = np.clip(b[:, 1], -1.5, 1.5)
    b[:, 2:4] = rng.uniform(0.05, 2.0, (n, 2))
    b[:, 4] = rng.uniform(-math.pi / 2, math.pi / 2, n)
    return a, b


def timed(fn):
    t = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--pairs", type=int, default=100_000)
    p.add_argument("--k", type=int, default=100, help="candidates NMS sees (decode's k)")
    p.add_argument("--threads", type=int, default=2)
    a_ = p.parse_args()
    torch.set_num_threads(a_.threads)
    a, b = random_pairs(a_.pairs)
    box_iou(a[:10], b[:10])
    exact, t64 = timed(lambda: box_iou(a, b, dtype=torch.float64))
    fast, t32 = timed(lambda: box_iou(a, b, dtype=torch.float32))
    n_loop = min(2000, a_.pairs)
    _, tloop = timed(lambda: [box_iou(a[i], b[i], dtype=torch.float64) for i in range(n_loop)])
    pts = fibonacci(200_000).pos.numpy()
    n_mc = min(200, a_.pairs)

    def sampled():
        ia, ib = points_in_boxes(pts, a[:n_mc]), points_in_boxes(pts, b[:n_mc])
        return (ia & ib).sum(0) / np.maximum((ia | ib).sum(0), 1)

    mc, tmc = timed(sampled)
    err = (fast.double() - exact).abs().numpy()
    mc_err = np.abs(mc - exact[:n_mc].numpy())
    print(f"{a_.pairs} random pairs, {float((exact > 0).float().mean()):.0%} overlapping\n")
    print("| method | us per pair | vs batched float32 | error vs float64 (max / 99% / median) |")
    print("|---|---|---|---|")
    us = 1e6 / a_.pairs
    print(f"| batched float32 (fast path) | {t32 * us:.2f} | 1.0 | {err.max():.1e} / "
          f"{np.quantile(err, 0.99):.1e} / {np.median(err):.1e} |")
    print(f"| batched float64 (exact reference) | {t64 * us:.2f} | {t64 / t32:.1f} | 0 |")
    print(f"| per-pair loop, float64 | {tloop * 1e6 / n_loop:.1f} | "
          f"{tloop / n_loop / (t32 / a_.pairs):.0f} | 0 |")
    print(f"| sampling, 200k points | {tmc * 1e6 / n_mc:.0f} | {tmc / n_mc / (t32 / a_.pairs):.0f} | "
          f"{mc_err.max():.1e} / {np.quantile(mc_err, 0.99):.1e} / {np.median(mc_err):.1e} |")
    nms_table(a_.k)


def nms_table(k: int) -> None:
    """NMS over ``k`` candidates anywhere on the sphere (as an untrained detector's, or a
    frame's objects), in a tenth and in all of them live."""
    boxes = torch.as_tensor(random_pairs(k, seed=1)[0])
    classes = torch.as_tensor(np.random.default_rng(2).integers(0, 12, k))
    every = box_iou(boxes[:, None], boxes[None])
    caps = pairwise_box_iou(boxes, boxes)
    t_every = best_time(lambda: box_iou(boxes[:, None], boxes[None]), 5)
    t_caps = best_time(lambda: pairwise_box_iou(boxes, boxes), 5)
    print(f"\nNMS over {k} candidates (float64; best of 5; same IoUs: "
          f"{bool(torch.equal(every, caps))})\n")
    print("| step | every pair / row, ms | caps meet / live rows, ms | ratio |")
    print("|---|---|---|---|")
    print(f"| IoU matrix, {k}x{k} | {t_every * 1e3:.2f} | {t_caps * 1e3:.2f} | "
          f"{t_every / t_caps:.1f}x |")
    for share in (0.1, 1.0):
        alive = torch.arange(k) < max(1, round(share * k))
        run = lambda alive=alive: nms_keep(boxes, alive, 0.5, classes)  # noqa: E731
        live, t_live = run(), best_time(run, 5)
        check, iou.check_values = iou.check_values, lambda: False  # the exported form
        try:
            fixed, t_fixed = run(), best_time(run, 5)
        finally:
            iou.check_values = check
        assert torch.equal(fixed, live)
        print(f"| NMS, {share:.0%} live | {t_fixed * 1e3:.2f} | {t_live * 1e3:.2f} | "
              f"{t_fixed / t_live:.1f}x |")


if __name__ == "__main__":
    main()
