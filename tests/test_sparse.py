"""Geometry buffers: converted to a call's dtype once and never stale; a sparse matrix's
members kept with storage of their own."""

import torch

from usf_graph.sparse import buffer_as, csr, csr_parts


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


def test_csr_parts_rebuild_the_matrix_and_alias_nothing():
    row, col = torch.tensor([0, 0, 2, 1]), torch.tensor([1, 3, 0, 1])
    A = csr(row, col, torch.tensor([1.0, 2.0, 3.0, 4.0]), (3, 4))
    crow, cols, val = csr_parts(A)
    B = torch.sparse_csr_tensor(crow, cols, val, (3, 4))
    assert torch.equal(B.to_dense(), A.to_dense())
    for part in (crow, cols, val):
        assert part._base is None  # a view of the sparse tensor stops torch.compile
    val.mul_(2)  # and editing a part leaves the matrix alone
    assert torch.equal(A.values(), torch.tensor([1.0, 2.0, 4.0, 3.0]))
