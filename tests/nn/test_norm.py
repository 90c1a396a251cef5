"""MaskedBatchNorm: statistics over visible points; static and PyG forms agree."""
import pytest
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


def test_masked_batchnorm_pyg_batch_equals_static_form_and_each_graph_in_eval():
    from torch_geometric.data import Batch, Data

    gen = torch.Generator().manual_seed(0)
    n = 40
    datas = [Data(x=torch.randn(n, 3, generator=gen) * 3 + 1, area=torch.rand(n, generator=gen),
                  mask=torch.rand(n, generator=gen) > p) for p in (0.1, 0.5)]
    b = Batch.from_data_list(datas)
    bn = MaskedBatchNorm(3)
    y = bn(b.x, b.mask, b.area, batch=b.batch)
    w = (b.area * b.mask)[:, None]  # statistics over every visible point of both graphs
    mean = (b.x * w).sum(0) / w.sum()
    var = (((b.x - mean) ** 2) * w).sum(0) / w.sum()
    torch.testing.assert_close(y, (b.x - mean) / torch.sqrt(var + 1e-5), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(bn.running_mean, mean * 0.1)
    # the static form [B, N, C] with per-sample masks [B, N] and shared areas [N]
    a = datas[0].area
    static = MaskedBatchNorm(3)(b.x.view(2, n, 3), b.mask.view(2, n), a)
    torch.testing.assert_close(static.reshape(-1, 3),
                               MaskedBatchNorm(3)(b.x, b.mask, a.repeat(2), batch=b.batch))
    bn.eval()
    y = bn(b.x, b.mask, b.area, batch=b.batch)
    for i, d in enumerate(datas):
        torch.testing.assert_close(y[b.batch == i], bn(d.x, d.mask, d.area))
    with pytest.raises(ValueError, match="one value per point"):
        bn(b.x, torch.ones(3, dtype=torch.bool))


def test_masked_batchnorm_matches_torch_batchnorm_with_gradients():
    """Without mask and weights it is torch's BatchNorm (biased variance in the output,
    running statistics aside): outputs and gradients, in training and evaluation."""
    gen = torch.Generator().manual_seed(3)
    x = (torch.randn(4, 30, 5, generator=gen, dtype=torch.float64) * 3 + 1).requires_grad_()
    ours, ref = MaskedBatchNorm(5).double(), torch.nn.BatchNorm1d(5).double()
    with torch.no_grad():
        for m in (ours, ref):
            m.weight.copy_(torch.linspace(0.5, 2, 5))
            m.bias.copy_(torch.linspace(-1, 1, 5))
    up = torch.randn(4, 30, 5, generator=gen, dtype=torch.float64)
    for train in (True, False):
        ours.train(train), ref.train(train)
        if not train:  # the same running statistics
            ours.running_mean.copy_(ref.running_mean)
            ours.running_var.copy_(ref.running_var)
        y = ours(x)
        y_ref = ref(x.transpose(1, 2)).transpose(1, 2)
        torch.testing.assert_close(y, y_ref, rtol=1e-12, atol=1e-12)
        g, g_ref = (torch.autograd.grad((t * up).sum(), [x, ours.weight if t is y else ref.weight])
                    for t in (y, y_ref))
        for a, b in zip(g, g_ref):
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)


def test_masked_batchnorm_reset_and_refusals():
    """``reset_parameters`` returns a trained layer to a new one's state; wrong shapes are
    refused by name."""
    bn = MaskedBatchNorm(3)
    with torch.no_grad():
        bn.weight.mul_(2)
        bn.bias.add_(1)
    bn(torch.randn(2, 40, 3) * 4 + 2)  # moves the running statistics
    bn.reset_parameters()
    for (name, got), want in zip(bn.state_dict().items(), MaskedBatchNorm(3).state_dict().values()):
        assert torch.equal(got, want), name
    x = torch.randn(2, 40, 3)
    for call, why in ((lambda: bn(x[..., :2]), r"x must be \[N, 3\], \[B, N, 3\]"),
                      (lambda: bn(x[None]), r"got \(1, 2, 40, 3\)"),
                      (lambda: bn(x, batch=torch.zeros(40, dtype=torch.long)),
                       r"batch must be \[sum N_i\] for x \[sum N_i, C\], got batch \(40,\)"),
                      (lambda: bn(x[0], batch=torch.zeros(39, dtype=torch.long)), r"got batch \(39,\)"),
                      (lambda: bn(x[0], mask=torch.ones(2, 40, dtype=torch.bool)),
                       r"mask must have one value per point \(40\), got \(2, 40\)"),
                      (lambda: bn(x, node_weight=torch.ones(1, 2, 40)), r"node_weight must have")):
        with pytest.raises(ValueError, match=why):
            call()
