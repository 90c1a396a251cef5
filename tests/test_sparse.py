"""Geometry buffers: converted to a call's dtype once and never stale; a sparse matrix's
members kept with storage of their own."""

import pytest
import torch

from usf_graph import sparse
from usf_graph.sparse import buffer_as, csr, csr_parts, index_dtype, transpose_csr


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
    # int32 indices, which torch's CPU sparse products take without converting them on
    # every call; int64 past 2**31 (the switch lowered to test it)
    assert crow.dtype == cols.dtype == torch.int32
    with pytest.MonkeyPatch.context() as m:
        m.setattr(sparse, "INT32_LIMIT", 4)
        assert index_dtype(3, 3) == torch.int32 and index_dtype(3, 4) == torch.int64
        assert csr_parts(A)[0].dtype == csr_parts(A)[1].dtype == torch.int64


@pytest.mark.parametrize("duplicates", [False, True])
def test_csr_from_entries_in_any_order_is_the_coalesced_matrix(duplicates):
    """Entries in any order give the sorted CSR matrix of their dense sum, with the values'
    gradient; repeated entries (summed) take the coalescing path. The transpose too."""
    gen = torch.Generator().manual_seed(0)
    key = torch.randperm(40 * 30, generator=gen)[:300]
    if duplicates:
        key = torch.cat([key, key[:20]])
    row, col = key // 30, key % 30
    val = torch.randn(len(key), dtype=torch.float64, generator=gen).requires_grad_()
    A = csr(row, col, val, (40, 30))
    dense = torch.zeros(40, 30, dtype=torch.float64).index_put((row, col), val, accumulate=True)
    assert torch.equal(A.to_dense(), dense.detach())
    c = A.crow_indices()
    for r in range(40):  # each row's columns ascending, none twice
        assert bool((A.col_indices()[c[r]:c[r + 1]].diff() > 0).all())
    w = torch.randn(30, 2, dtype=torch.float64, generator=gen)
    (g,) = torch.autograd.grad((A @ w).square().sum(), val)
    (want,) = torch.autograd.grad((dense @ w).square().sum(), val)
    torch.testing.assert_close(g, want, rtol=1e-12, atol=1e-12)
    At = transpose_csr(A.detach())
    assert At.layout == torch.sparse_csr and torch.equal(At.to_dense(), dense.detach().t())


def test_the_layers_sparse_operators_take_int32_indices():
    """The pools', jets', convolutions' and (rows of varying length: area lifting, soft
    labels) interpolation tables' CSR matrices."""
    from usf_graph import grids
    from usf_graph.frontend.frontend import _Table
    from usf_graph.nn import GaussianPool, LocalJet, SphericalConv, geodesic_radius_graph

    g = grids.icosahedral(2)
    pool = GaussianPool(g.pos, grids.icosahedral(1).pos, 0.3)
    ei, ew = geodesic_radius_graph(g.pos, 3.5 * g.spacing)
    jet = LocalJet(g.pos, ei, ew, g.spacing)
    conv = SphericalConv(2, 3, 3.5 * g.spacing).bind(ei, ew)
    conv(torch.rand(1, len(g), 2))
    parts = [pool.crow, pool.col, *(t for k, t in jet.named_buffers() if k.endswith(("crow", "col")))]
    parts += [t for k, t in conv.plan.named_buffers() if k.startswith(("crow", "col"))]
    table = _Table(torch.tensor([0, 1, 3]), torch.tensor([2, 0, 1]), torch.ones(3), 4)
    parts += [table.csr.crow_indices(), table.csr.col_indices()]
    assert len(parts) >= 10 and all(t.dtype == torch.int32 for t in parts)
    assert torch.equal(table.apply(torch.arange(4.0)[:, None]), torch.tensor([[2.0], [1.0]]))


# -- the padded layout of the plain forms (usf_graph.tracing) --------------------------------

from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from usf_graph.sparse import padded_operator, padded_product, padded_rows, padded_values  # noqa: E402


def _random_csr(seed: int, rows: int, cols: int, density: float, group: int = 1,
                shared: bool = True):
    """A random sparse ``[rows * group, cols]`` matrix (empty rows included), dense and as
    CSR parts; with ``group`` > 1 and ``shared`` each block of ``group`` rows shares its
    columns (otherwise every row draws its own)."""
    gen = torch.Generator().manual_seed(seed)
    if shared:
        pattern = (torch.rand(rows, cols, generator=gen) < density).repeat_interleave(group, 0)
    else:
        pattern = torch.rand(rows * group, cols, generator=gen) < density
    dense = torch.randn(rows * group, cols, generator=gen, dtype=torch.float64) * pattern
    A = dense.to_sparse_csr()
    return dense, A.crow_indices(), A.col_indices(), A.values()


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), rows=st.integers(1, 12), cols=st.integers(1, 9),
       density=st.floats(0.0, 1.0), group=st.sampled_from([1, 2, 5]), feat=st.integers(1, 3),
       shared=st.booleans())
def test_padded_product_is_the_matrix_product(seed, rows, cols, density, group, feat, shared):
    dense, crow, col, val = _random_csr(seed, rows, cols, density, group, shared)
    c, slot = padded_rows(crow, col, group)
    assert c.dtype == slot.dtype == torch.int32
    x = torch.randn(cols, 2, feat, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    y = padded_product(c, padded_values(val, slot), x)
    want = (dense @ x.reshape(cols, -1)).reshape(-1, 2, feat)
    assert y.shape == want.shape and (y - want).abs().max() < 1e-12
    # the rows of a block that hold the same columns are gathered once; others one by one
    blocks = (dense != 0).reshape(rows, group, cols)
    alike = bool((blocks == blocks[:, :1]).all()) and len(val) > 0
    assert slot.shape[:2] == ((rows, group) if alike else (rows * group, 1))
    assert c.shape[0] == slot.shape[0]


def test_blocks_with_different_columns_are_laid_out_row_by_row():
    dense = torch.tensor([[1.0, 0.0, 2.0], [0.0, 3.0, 4.0], [5.0, 0.0, 0.0], [6.0, 0.0, 0.0]],
                         dtype=torch.float64)
    A = dense.to_sparse_csr()
    cols, slot = padded_rows(A.crow_indices(), A.col_indices(), group=2)
    assert slot.shape[1] == 1  # rows 0 and 1 differ: no sharing
    x = torch.randn(3, 2, dtype=torch.float64)
    assert torch.allclose(padded_product(cols, padded_values(A.values(), slot), x), dense @ x)
    B = dense[1:].to_sparse_csr()  # 3 rows do not split into blocks of 2
    cols, slot = padded_rows(B.crow_indices(), B.col_indices(), group=2)
    assert slot.shape[:2] == (3, 1)
    assert torch.allclose(padded_product(cols, padded_values(B.values(), slot), x), dense[1:] @ x)


def test_padded_operators_share_one_layout_and_follow_edits():
    dense, crow, col, val = _random_csr(3, 6, 5, 0.5)
    a, b = torch.nn.Module(), torch.nn.Module()
    for m in (a, b):  # two modules holding the same operator, as the jets of one graph do
        for name, t in (("op_crow", crow), ("op_col", col), ("op_val", val)):
            m.register_buffer(name, t, persistent=False)
    ca, wa = padded_operator(a, "op", torch.float32)
    cb, wb = padded_operator(b, "op", torch.float32)
    assert ca is cb and wa is wb and wa.dtype == torch.float32
    x = torch.randn(5, 3, dtype=torch.float64)
    assert (padded_product(*padded_operator(a, "op", torch.float64), x) - dense @ x).abs().max() < 1e-12
    c = torch.nn.Module()
    for name, t in (("op_crow", crow), ("op_col", col), ("op_val", val.clone())):
        c.register_buffer(name, t, persistent=False)
    c.op_val.mul_(2.0)  # new values: a layout of its own
    assert (padded_product(*padded_operator(c, "op", torch.float64), x) - 2 * dense @ x).abs().max() < 1e-12


def test_two_equal_entries_are_summed_into_one():
    """The smallest matrix with a repeated entry: two entries, one place."""
    A = csr(torch.tensor([1, 1]), torch.tensor([2, 2]), torch.tensor([2.0, 3.0]), (3, 4))
    assert A.values().tolist() == [5.0] and A.col_indices().tolist() == [2]
    assert A.crow_indices().tolist() == [0, 0, 1, 1]


def test_padded_tables_stay_out_of_the_state_dict():
    """The padded layout is rebuilt from the CSR buffers on first use; kept in the state
    dict it would make checkpoints written after a forward pass refuse to load into a
    fresh model (unexpected keys)."""
    _, crow, col, val = _random_csr(4, 6, 5, 0.5)
    m = torch.nn.Module()
    for name, t in (("op_crow", crow), ("op_col", col), ("op_val", val)):
        m.register_buffer(name, t)
    before = set(m.state_dict())
    padded_operator(m, "op", torch.float32)
    assert set(m.state_dict()) == before == {"op_crow", "op_col", "op_val"}
