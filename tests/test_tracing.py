"""What layers do while exported: the plain forms give the fast forms' outputs and
gradients on every model, and the fields of view an export is bound to are recorded by
value and never confused."""

import numpy as np
import pytest
import torch

from tests.models.test_gray import SPHERICAL, _flat, _input
from usf_graph import tracing


def test_fields_are_recorded_by_size_and_two_masks_of_one_size_refused():
    a = torch.tensor([True, False, True])
    with tracing.fixed_fields() as rec:
        assert tracing.plain_forms()  # the recording call builds the plain forms' tables
        assert np.array_equal(tracing.field_of(a), a.numpy())
        tracing.note_field(torch.ones(5, dtype=torch.bool))
        tracing.field_of(a.clone())  # the same values again: fine
        with pytest.raises(ValueError, match="two different fields of view of 3 points"):
            tracing.field_of(torch.tensor([True, True, False]))
    assert set(rec) == {3, 5} and rec[5].all()
    assert not tracing.plain_forms()
    tracing.note_field(a)  # outside a recording: nothing kept, nothing raised
    assert np.array_equal(tracing.field_of(~a), [False, True, False])


def test_an_export_without_recorded_fields_says_how_to_record_them():
    class ReadsItsField(torch.nn.Module):
        def forward(self, x, mask):
            return x * bool(tracing.field_of(mask).all())

    args = (torch.ones(3), torch.tensor([True, False, True]))
    with pytest.raises(RuntimeError, match="no recorded field of view of 3 points"):
        torch.export.export(ReadsItsField(), args)
    with tracing.fixed_fields() as rec:
        ReadsItsField()(*args)
    with tracing.fixed_fields(rec):
        program = torch.export.export(ReadsItsField(), args)
    assert torch.equal(program.module()(*args), torch.zeros(3))


def test_what_a_trace_or_a_transform_cannot_read_is_refused_or_skipped():
    """Value checks run eagerly only; under a torch.func transform a field of view cannot be
    read, and while exporting tables are built by an eager call first."""
    seen = {}

    def f(x, key):
        seen[key] = (tracing.check_values(), tracing.transforming())
        return x.sum()

    x, mask = torch.ones(3), torch.tensor([True, False, True])
    f(x, "eager")
    torch.func.grad(f)(x, "grad")
    torch.func.vmap(f, in_dims=(0, None))(x[None], "vmap")
    assert seen == {"eager": (True, False), "grad": (False, True), "vmap": (False, True)}
    with pytest.raises(RuntimeError, match="cannot be read under a torch.func transform"):
        torch.func.grad(lambda t: t.sum() * float(tracing.field_of(mask).all()))(x)

    class Builds(torch.nn.Module):
        def forward(self, t):
            seen["export"] = tracing.check_values()
            tracing.require_eager("its padded tables")
            return t

    tracing.require_eager("anything")  # eagerly: nothing to refuse
    with pytest.raises(RuntimeError, match="its padded tables are built by an eager call first"):
        torch.export.export(Builds(), (x,))
    assert seen["export"] is False
    with tracing.fixed_fields() as rec:
        tracing.note_field(None)  # no mask: nothing recorded
    assert rec == {}


@pytest.mark.parametrize("cls, kw", SPHERICAL, ids=[c.__name__ for c, _ in SPHERICAL])
def test_plain_forms_give_the_fast_forms_outputs_and_gradients(cls, kw):
    """Every spherical model, float64, a new field of view on every call, its up estimate
    and a given up: the same outputs (1e-10) and input gradients in both forms."""
    torch.manual_seed(0)
    model = cls(**kw).double().eval()
    for seed in range(2):
        x, mask, _ = _input(cls, kw, seed)
        for up in (None, torch.nn.functional.normalize(torch.randn(len(x), 3, dtype=torch.float64), dim=1)):
            xs = [x.clone().requires_grad_() for _ in range(2)]
            outs = []
            for form, xi in zip((False, True), xs):
                ctx = tracing.plain() if form else torch.enable_grad()
                with ctx:
                    out = model(xi, mask) if up is None else model(xi, mask, up=up)
                outs.append([t for t in _flat(out) if t.is_floating_point()])
            # the plain forms ran: their padded tables exist now
            assert any(hasattr(m, "pad_col") for m in model.modules())
            for a, b in zip(*outs):
                assert (a - b).abs().max() < 1e-10 * (1 + b.abs().max()), (seed, up is None)
            loss = [sum((t * torch.linspace(-1, 1, t.numel(), dtype=t.dtype).view(t.shape)).sum()
                        for t in o if t.requires_grad) for o in outs]
            ga, gb = (torch.autograd.grad(l_, xi) for l_, xi in zip(loss, xs))
            assert (ga[0] - gb[0]).abs().max() < 1e-9 * (1 + gb[0].abs().max())


def test_jets_and_pools_under_torch_func_and_forward_mode_give_autograds_answers():
    """Under ``torch.func`` and forward-mode AD the jet and the pool take their plain forms
    (sparse tensors serve neither): ``jacrev``, ``vmap`` and ``jvp`` give the Jacobian
    that ordinary autograd builds through the sparse form, and its products."""
    import torch.autograd.forward_ad as fwAD
    from torch.autograd.functional import jacobian
    from torch.func import jacrev, jvp, vmap

    from usf_graph import grids
    from usf_graph.frontend import grid_graph
    from usf_graph.nn import GaussianPool, LocalJet

    g = grids.icosahedral(1)
    coarse, _ = g.coarsen()
    ei, ew = grid_graph(g, 3.5 * g.spacing)
    jet = LocalJet(g.pos, ei, ew, g.spacing).double()
    pool = GaussianPool(g.pos, coarse.pos, 0.5 * coarse.spacing, area=g.area).double()
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(1, len(g), 2, dtype=torch.float64, generator=gen)
    v = torch.randn(x.shape, dtype=torch.float64, generator=gen)
    for f in (jet, lambda t: pool(t)[0]):
        assert not tracing.plain_forms(x)
        J = jacobian(f, x)  # the sparse form's autograd
        torch.testing.assert_close(jacrev(f)(x), J, atol=1e-12, rtol=0)
        Jv = torch.einsum("...ijk,ijk->...", J, v)
        torch.testing.assert_close(jvp(f, (x,), (v,))[1], Jv, atol=1e-12, rtol=0)
        with fwAD.dual_level():
            tangent = fwAD.unpack_dual(f(fwAD.make_dual(x, v))).tangent
        torch.testing.assert_close(tangent, Jv, atol=1e-12, rtol=0)
        xs = torch.cat([x, v])
        torch.testing.assert_close(vmap(f)(xs[:, None]), f(xs)[:, None], atol=1e-12, rtol=0)
