"""Geometry buffers converted to a call's dtype once, and never stale."""

import torch

from usf_graph.sparse import buffer_as


def test_buffer_as_converts_once_and_follows_edits_and_to():
    m = torch.nn.Module()
    m.register_buffer("val", torch.linspace(0, 1, 7, dtype=torch.float64))
    assert buffer_as(m, "val", torch.float64) is m.val  # its own dtype: the buffer itself
    a = buffer_as(m, "val", torch.float32)
    assert a.dtype == torch.float32 and torch.equal(a, m.val.float())
    assert buffer_as(m, "val", torch.float32) is a  # converted once
    m.val.mul_(3)  # an in-place edit: converted again
    b = buffer_as(m, "val", torch.float32)
    assert b is not a and torch.equal(b, m.val.float())
    m.to(torch.float16)  # .to() replaces the buffer: converted from the new one
    c = buffer_as(m, "val", torch.float32)
    assert c is not b and torch.equal(c, m.val.float())
