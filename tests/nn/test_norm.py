"""MaskedBatchNorm: statistics over visible points; static and PyG forms agree."""


import torch

from usf_graph.nn import (
    MaskedBatchNorm,
    global_mean_pool_area,
)


def test_masked_batchnorm_and_global_pool():
    x = torch.randn(3, 50, 4) * 5 + 2
    mask = torch.arange(50) < 30
    bn = MaskedBatchNorm(4)
    y = bn(x, mask)
    torch.testing.assert_close(y[:, mask].mean((0, 1)), torch.zeros(4), atol=1e-10, rtol=0)
    torch.testing.assert_close(y[:, mask].var((0, 1), unbiased=False), torch.ones(4), atol=1e-3, rtol=0)
    area = torch.rand(50)
    gm = global_mean_pool_area(x, area, mask)
    torch.testing.assert_close(gm, (x[:, mask] * area[mask, None]).sum(1) / area[mask].sum())
