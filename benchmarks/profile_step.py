"""Where a training step of the protocol's spherical U-Net spends its time: PyTorch's
profiler over a few steps (forward, backward, Adam), its ops sorted by device time, and
the number of kernels launched per step. On a GPU the step is launch-bound (benchmarks/
README.md), so the launch count matters as much as the time.

    python benchmarks/profile_step.py [--device cuda] [--batch 32] [--level 5] [--steps 3]
                                      [--model spherical_unet|spherical_deeplab] [--rows 25]
"""

from __future__ import annotations

import argparse

import torch
from torch.profiler import ProfilerActivity, profile

from usf_graph.train.seg import make_model, segmentation_loss


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--level", type=int, default=5)
    p.add_argument("--steps", type=int, default=3)
    p.add_argument("--rows", type=int, default=25)
    p.add_argument("--model", default="spherical_unet", choices=["spherical_unet", "spherical_deeplab"])
    a = p.parse_args()
    dev = torch.device(a.device)
    torch.manual_seed(0)
    net = make_model(a.model, a.level).to(dev)
    net.gravity.requires_grad_(False)  # frozen, as in training: the step reads the known up
    B, N = a.batch, net.num_points
    x, y = torch.rand(B, N, 3, device=dev), torch.randint(0, 13, (B, N), device=dev)
    up = torch.tensor([[0.0, 0.0, 1.0]], device=dev).expand(B, 3)
    opt = torch.optim.Adam([q for q in net.parameters() if q.requires_grad], 1e-3)

    def step():
        opt.zero_grad(set_to_none=True)
        segmentation_loss(net(x, up=up), y).backward()
        opt.step()

    for _ in range(3):
        step()
    cuda = dev.type == "cuda"
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    if cuda:
        torch.cuda.synchronize(dev)
    with profile(activities=acts) as prof:
        for _ in range(a.steps):
            step()
        if cuda:
            torch.cuda.synchronize(dev)
    key = "self_cuda_time_total" if cuda else "self_cpu_time_total"
    print(prof.key_averages().table(sort_by=key, row_limit=a.rows))
    if cuda:
        kernels = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
        busy = sum(e.device_time for e in kernels) / 1e3 / a.steps
        print(f"{len(kernels) / a.steps:.0f} kernels per step, {busy:.1f} ms of kernel time per step")


if __name__ == "__main__":
    main()
