"""What layers do differently while ``torch.export`` (and so ``torch.onnx.export``) traces
them (:mod:`usf_graph.train.export`).

A traced call sees fake tensors: it cannot read values, so it cannot branch on them, check
them or build geometry from them. So:

* sparse products take their plain forms (:func:`plain`: gathers into rows padded to one
  length and batched matrix products, :func:`usf_graph.sparse.padded_product`), whose
  index tables an eager call builds first (:func:`fixed_fields` records in that form);
* checks that read values are skipped (:func:`check_values`);
* the decisions a layer takes from its field of view (which points to fill, which cached
  coefficients apply) read the masks that eager call recorded, real arrays: an exported
  model is bound to one camera's field of view, as its lifting table is.
"""

from __future__ import annotations

import contextlib

import numpy as np
import torch
from torch.autograd import forward_ad

_FIELDS: list[dict] = []  # the fields of view, by size, of the recording or export in progress
_PLAIN = [0]  # depth of plain() contexts


def exporting() -> bool:
    """Whether ``torch.export`` is tracing the call."""
    return torch.compiler.is_exporting()


@contextlib.contextmanager
def fixed_fields(fields: dict | None = None):
    """Without ``fields``: record, in the dict yielded, the field of view of every size
    that eager calls inside read through :func:`field_of` (a model's input mask and those
    its pooling derives on coarser grids). With ``fields`` (such a record): export inside,
    :func:`field_of` answering from it. An exported model is bound to one camera's field
    of view, as its lifting table is; two different masks of one size in one recorded
    call are refused, since the record could not tell them apart."""
    record = {} if fields is None else fields
    _FIELDS.append({"fields": record, "recording": fields is None})
    try:
        with plain():
            yield record
    finally:
        _FIELDS.pop()


@contextlib.contextmanager
def plain():
    """Layers take their plain forms inside (as they do while exporting): the eager
    reference of an exported model, and what builds the forms' index tables."""
    _PLAIN[0] += 1
    try:
        yield
    finally:
        _PLAIN[0] -= 1


def transforming() -> bool:
    """Whether a ``torch.func`` transform (``grad``, ``vmap``, ...) is active; never inside
    ``torch.compile``'s trace, which would break its graph on the question."""
    return not torch.compiler.is_compiling() and torch._C._are_functorch_transforms_active()


def plain_forms(*tensors: torch.Tensor) -> bool:
    """Whether layers take their plain forms: while exporting, inside :func:`plain`, under
    a ``torch.func`` transform (``grad``, ``vmap``, ``jacrev``, ...), or where any of
    ``tensors`` (the call's inputs) carries a forward-mode tangent
    (``torch.autograd.forward_ad``). Sparse tensors and the fast forms' hand-written
    backward serve none of these; the plain forms are autograd's own, in every mode."""
    if _PLAIN[0] > 0 or exporting() or transforming():
        return True
    if torch.compiler.is_compiling():
        return False
    return any(forward_ad.unpack_dual(t).tangent is not None for t in tensors)


def field_of(mask: torch.Tensor) -> np.ndarray:
    """``mask``'s values as a numpy bool array ``[N]``, for the decisions a layer takes
    from its field of view: ``mask``'s own, or, while exporting, the recorded field of its
    size (:func:`fixed_fields`)."""
    state = _FIELDS[-1] if _FIELDS else None
    n = int(mask.shape[-1]) if mask.dim() else 0
    if exporting():
        if state is None or n not in state["fields"]:
            raise RuntimeError(f"no recorded field of view of {n} points: a masked model is "
                               "exported inside tracing.fixed_fields(record), after an eager "
                               "call recorded its fields (usf_graph.train.export does this)")
        return state["fields"][n]
    if transforming():  # its tensors' values cannot be read
        raise RuntimeError("a model's field of view (its mask) cannot be read under a "
                           "torch.func transform: call it there with mask=None (every point "
                           "seen), or take gradients with ordinary autograd")
    m = mask.detach().cpu().numpy().astype(bool, copy=False)
    if state is not None and state["recording"]:
        seen = state["fields"].setdefault(n, m.copy())
        if seen.shape != m.shape or not np.array_equal(seen, m):
            raise ValueError(f"two different fields of view of {n} points in one call: an "
                             "export cannot be bound to either")
    return m


def note_field(mask: torch.Tensor | None) -> None:
    """Record ``mask`` while :func:`fixed_fields` records (a layer that reads its field of
    view through :func:`field_of` only while exporting); otherwise nothing, and no copy."""
    if mask is not None and _FIELDS and _FIELDS[-1]["recording"] and not exporting():
        field_of(mask)


def require_eager(what: str) -> None:
    """Refuse to build ``what`` while exporting: a traced call sees no values to build it
    from, so an eager call inside :func:`fixed_fields` must build it first."""
    if exporting():
        raise RuntimeError(f"{what} are built by an eager call first: export inside "
                           "usf_graph.tracing.fixed_fields, after one eager call there "
                           "(usf_graph.train.export does this)")


def check_values() -> bool:
    """Whether checks that read values (NaN, empty fields of view) can run: not while
    exporting (an exported model checks its own inputs, :mod:`usf_graph.train.export`),
    nor under a ``torch.func`` transform, whose ``vmap`` cannot branch on values (a NaN
    input then shows as NaN outputs instead of an error)."""
    return not exporting() and not transforming()
