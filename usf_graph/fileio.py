"""Atomic file writes: a temp file in the target's folder, then ``os.replace``.

Readers never see a partial file, concurrent writers of one path each leave a complete
one, and a failed write removes its temp file.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO


def atomic_write(path, write: Callable[[IO], None], mode: str = "wb") -> None:
    """Create ``path``'s folder, call ``write(f)`` on a temp file opened with ``mode``, and
    move it onto ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, mode) as f:
            write(f)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_torch_save(obj, path) -> None:
    """``torch.save(obj, path)``, atomically."""
    import torch

    atomic_write(path, lambda f: torch.save(obj, f))
