"""Quiet use of torch's sparse CSR tensors."""

from __future__ import annotations

import contextlib
import warnings


@contextlib.contextmanager
def quiet_sparse():
    """Silence torch's "Sparse CSR tensor support is in beta" and "Sparse invariant checks"
    UserWarnings, raised on every construction and use; other warnings still show."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse", category=UserWarning)
        yield
