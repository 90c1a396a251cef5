"""The protocol models under ``torch.compile``, ``torch.inference_mode`` and half precision
(a bfloat16 model, CPU autocast): each gives the plain model's outputs and gradients
(within half precision's rounding), call after call, as the camera's field of view
changes. Each meets the geometry the layers keep from call to call."""

import copy

import pytest
import torch

from usf_graph import grids
from usf_graph.models import SphericalDeepLabV3, SphericalDetector


def _flat(out) -> torch.Tensor:
    parts = out.values() if isinstance(out, dict) else [out]
    return torch.cat([p.flatten() for p in parts if torch.is_tensor(p) and p.is_floating_point()])


def DETECTOR():
    return SphericalDetector(12, input_level=3, head_level=2, min_level=1, channels=(8, 8, 8),
                             gravity=True, upright=True)


MODELS = pytest.mark.parametrize("build", [
    lambda: SphericalDeepLabV3(level=3, channels=(8, 8, 8), aspp_channels=8, low_channels=8,
                               gravity=True),
    DETECTOR,
], ids=["deeplab", "detector"])


def test_compiled_model_matches_eager_as_the_field_of_view_changes():
    # "eager" backend: Dynamo's tracing (where a buffer aliasing a sparse tensor's members
    # once failed) without Inductor's minute of C++ compilation. The detector has every
    # kind of layer (pools, jets, the up estimate, UprightConv); its trace takes 10 s.
    torch.manual_seed(0)
    model = DETECTOR()
    ref = copy.deepcopy(model)
    fast = torch.compile(model, backend="eager")
    n = len(grids.icosahedral(3))
    gen = torch.Generator().manual_seed(1)
    x = torch.rand(2, n, 3, generator=gen)
    up = torch.nn.functional.normalize(torch.randn(2, 3, generator=gen), dim=-1)
    seen = torch.rand(n, generator=gen) > 0.3
    other = torch.rand(n, generator=gen) > 0.5
    calls = [seen, None, seen.clone(), other, "edit", seen]
    model.eval(), ref.eval()
    for mask in calls:
        if isinstance(mask, str):  # the same tensor, edited in place
            other[: n // 3] = ~other[: n // 3]
            mask = other
        with torch.no_grad():
            torch.testing.assert_close(_flat(fast(x, mask=mask, up=up)),
                                       _flat(ref(x, mask=mask, up=up)), rtol=1e-5, atol=1e-6)
    model.train(), ref.train()
    for net in (fast, ref):
        _flat(net(x, mask=seen, up=up)).square().mean().backward()
    for (name, p), q in zip(model.named_parameters(), ref.parameters()):
        assert (p.grad is None) == (q.grad is None), name
        if p.grad is not None:
            torch.testing.assert_close(p.grad, q.grad, rtol=1e-4, atol=1e-6, msg=name)


@MODELS
def test_inference_mode_leaves_nothing_that_breaks_later_calls(build):
    """Deployment code runs models under ``torch.inference_mode()``, whose tensors have no
    version counter and cannot be saved for backward. What the layers keep from such a
    call (coefficients, tiles, converted buffers) must serve later calls in any mode: the
    model under test takes every evaluation in inference mode, its twin under no_grad."""
    torch.manual_seed(0)
    model = build()
    twin = copy.deepcopy(model)
    n = len(grids.icosahedral(3))
    gen = torch.Generator().manual_seed(2)
    x = torch.rand(2, n, 3, generator=gen)
    up = torch.nn.functional.normalize(torch.randn(2, 3, generator=gen), dim=-1)
    seen = torch.rand(n, generator=gen) > 0.3
    steps = [("eval", seen), ("eval", seen.clone()), ("eval", None), ("train", seen),
             ("eval", "edit"), ("train", None), ("eval", seen), ("train", "edit")]
    for kind, mask in steps:
        if isinstance(mask, str):  # the same tensor, edited in place
            seen[: n // 4] = ~seen[: n // 4]
            mask = seen
        if kind == "eval":
            model.eval(), twin.eval()
            with torch.inference_mode():
                out = _flat(model(x, mask=mask, up=up))
            with torch.no_grad():
                ref = _flat(twin(x, mask=mask, up=up))
            torch.testing.assert_close(out, ref, rtol=0, atol=0)
            continue
        model.train(), twin.train()
        for net in (model, twin):
            net.zero_grad()
            _flat(net(x, mask=mask, up=up)).square().mean().backward()
        for (name, p), q in zip(model.named_parameters(), twin.parameters()):
            assert (p.grad is None) == (q.grad is None), name
            if p.grad is not None:
                torch.testing.assert_close(p.grad, q.grad, rtol=0, atol=0, msg=name)


def _inputs(seed: int):
    """``(x [2, N, 3], up [2, 3], seen [N])`` on icosahedral:3, the models' test grid."""
    n = len(grids.icosahedral(3))
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(2, n, 3, generator=gen)
    up = torch.nn.functional.normalize(torch.randn(2, 3, generator=gen), dim=-1)
    return x, up, torch.rand(n, generator=gen) > 0.3


def _autocast_pair(model, x, up, seen, dtype):
    """``[(outputs, gradients)]`` of one training step without and with autocast to
    ``dtype`` on ``x``'s device."""
    runs = []
    for autocast in (False, True):
        with torch.autocast(x.device.type, dtype=dtype, enabled=autocast):
            out = _flat(model(x, mask=seen, up=up))
        out.float().square().mean().backward()
        runs.append((out, torch.cat([p.grad.flatten() for p in model.parameters()
                                     if p.grad is not None])))
        model.zero_grad()
    return runs


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.detach().float(), b.detach().float()
    return float((a - b).norm() / b.norm())


@MODELS
def test_half_precision_follows_float32(build):
    """A bfloat16 model and float32 under CPU autocast: torch's CPU sparse products have no
    half kernels, so the layers sum in float32 and hand back their input's dtype."""
    torch.manual_seed(0)
    model = build()
    x, up, seen = _inputs(3)
    (ref, g32), (low, g16) = _autocast_pair(model, x, up, seen, torch.bfloat16)
    assert _rel(low, ref) < 0.03 and _rel(g16, g32) < 0.15
    assert torch.isfinite(g16).all()
    half = copy.deepcopy(model).bfloat16().eval()
    model.eval()
    with torch.no_grad():
        ref = _flat(model(x, mask=seen, up=up))
        for mask in (seen, None, seen):  # cached float32 geometry serves each call
            low = _flat(half(x.bfloat16(), mask=mask, up=up.bfloat16()))
            assert low.dtype == torch.bfloat16
            if mask is not None:
                assert _rel(low, ref) < 0.03


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU (CI has none)")
@MODELS
def test_on_a_gpu_autocast_float16_follows_float32(build):
    """CUDA autocast in float16 (the usual mixed-precision training) against float32 on the
    same GPU: outputs and gradients within half precision's rounding."""
    torch.manual_seed(0)
    model = build().cuda()
    x, up, seen = (t.cuda() for t in _inputs(3))
    (ref, g32), (low, g16) = _autocast_pair(model, x, up, seen, torch.float16)
    assert _rel(low, ref) < 0.01 and _rel(g16, g32) < 0.05 and torch.isfinite(g16).all()


@MODELS
def test_per_sample_gradients_through_torch_func(build):
    """``vmap(grad)`` (per-sample gradients, as DP-SGD takes them) through a whole protocol
    model in evaluation mode, with an up per sample: each sample's gradient is the one
    ordinary autograd gives that sample alone (float64). A field of view, which the model
    reads by value, is refused there with a message that says so."""
    from torch.func import functional_call, grad, vmap

    torch.manual_seed(0)
    model = build().double().eval()
    n = len(grids.icosahedral(3))
    gen = torch.Generator().manual_seed(2)
    x = torch.rand(3, n, 3, generator=gen, dtype=torch.float64)
    up = torch.nn.functional.normalize(torch.randn(3, 3, generator=gen, dtype=torch.float64), dim=-1)
    seen = torch.rand(n, generator=gen) > 0.3
    params = {k: v.detach() for k, v in model.named_parameters()}
    buffers = dict(model.named_buffers())

    def loss(p, xb, ub):
        out = functional_call(model, (p, buffers), (xb[None],), {"mask": mask, "up": ub[None]})
        return _flat(out).square().mean()

    mask = seen
    with pytest.raises(RuntimeError, match="field of view .* cannot be read under a torch.func"):
        vmap(grad(loss), in_dims=(None, 0, 0))(params, x, up)
    mask = None
    per = vmap(grad(loss), in_dims=(None, 0, 0))(params, x, up)
    for b in (0, 2):
        want = torch.autograd.grad(loss(dict(model.named_parameters()), x[b], up[b]),
                                   list(model.parameters()), allow_unused=True)
        for (name, _), w in zip(model.named_parameters(), want):
            got = per[name][b]
            torch.testing.assert_close(got, torch.zeros_like(got) if w is None else w,
                                       rtol=1e-9, atol=1e-12, msg=name)
    # what the layers kept from calls under the transform (tables, coefficients) is plain
    # tensors, not the transform's wrappers, which outlive it and no export can save
    for t in model.buffers():
        t.untyped_storage()  # a wrapper raises here
