"""The per-pixel ray tables of the lenses seen lately, kept in memory.

A lens model's ``pixel_rays`` solves its inverse at every pixel (a Newton solve for most
fisheye and distortion models: a second for a large image). The same table serves every
copy of the camera that differs only in where it is mounted (rotation, position), and
every re-imager, frontend and leveler built on it, so it is computed once per lens.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable

import numpy as np

#: The most bytes of tables kept (the least recently used go first); a table larger than a
#: quarter of it is computed each time instead.
BUDGET_BYTES = 256 * 2**20

_TABLES: OrderedDict[str, tuple[np.ndarray, np.ndarray]] = OrderedDict()
_LOCK = threading.Lock()


def kept_rays(key: str, build: Callable[[], tuple[np.ndarray, np.ndarray]]
              ) -> tuple[np.ndarray, np.ndarray]:
    """``build()``'s ``(rays [H, W, 3], valid [H, W])`` for the lens ``key`` (its
    :meth:`~usf_graph.cameras.base.Camera.lens_key`, as JSON), computed once while it is
    kept; each call gets its own copies to change as it likes."""
    with _LOCK:
        table = _TABLES.get(key)
        if table is not None:
            _TABLES.move_to_end(key)
    if table is None:
        table = tuple(np.asarray(a) for a in build())
        size = sum(a.nbytes for a in table)
        if size <= BUDGET_BYTES // 4:
            with _LOCK:
                _TABLES[key] = table
                while sum(a.nbytes for t in _TABLES.values() for a in t) > BUDGET_BYTES:
                    _TABLES.popitem(last=False)
    return table[0].copy(), table[1].copy()


def forget_rays() -> None:
    """Drop every kept table (they are rebuilt on next use)."""
    with _LOCK:
        _TABLES.clear()
