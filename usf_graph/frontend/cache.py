"""Geometry cache: in memory (LRU) and on disk, keyed by a hash of everything it depends on.

Files are written atomically (temp file + rename), validated on load, and rebuilt with a
warning when corrupt or mismatched, so two processes may fill the same key at once.
"""

from __future__ import annotations

import hashlib
import json
import os
import warnings
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from .._version import __version__
from ..fileio import atomic_write
from ..sparse import kept

# Part of every key: bump it whenever cached geometry changes meaning, so tables written by
# an older convention are never read again (2: panoramas no longer mirrored; 3: pixels
# without a ray no longer blend into their neighbours; 4: a lens normal map sees its
# image's outer half pixel; 5: a fisheye no longer sees the direction straight behind it).
GEOMETRY_VERSION = 5


def default_cache_dir() -> Path | None:
    """``$USF_GRAPH_CACHE`` (``off`` disables the disk cache), else ``~/.cache/usf_graph``."""
    env = os.environ.get("USF_GRAPH_CACHE")
    if env is not None and env.strip().lower() in ("", "off", "none", "0"):
        return None
    return Path(env).expanduser() if env else Path.home() / ".cache" / "usf_graph"


class GeometryCache:
    """Maps (kind, key dict) -> dict of tensors; ``builds`` counts actual computations."""

    def __init__(self, directory: str | Path | None = "default", max_items: int = 32):
        self.directory = default_cache_dir() if directory == "default" else (
            Path(directory) if directory is not None else None)
        self.max_items = max_items
        self._mem: OrderedDict[str, dict] = OrderedDict()
        self.builds = 0
        self.hits = 0

    @staticmethod
    def digest(kind: str, key: dict) -> str:
        """SHA-256 of the kind, the key, the package version and :data:`GEOMETRY_VERSION`."""
        blob = json.dumps({"kind": kind, "key": key, "version": __version__,
                           "geometry": GEOMETRY_VERSION}, sort_keys=True,
                          default=str)
        return hashlib.sha256(blob.encode()).hexdigest()

    def path(self, kind: str, key: dict) -> Path | None:
        """The file that holds ``(kind, key)`` on disk, or None without a disk cache."""
        if self.directory is None:
            return None
        return self.directory / f"{kind}-{self.digest(kind, key)[:32]}.npz"

    def get(self, kind: str, key: dict, build: Callable[[], dict]) -> dict:
        """The tensors for ``(kind, key)``: from memory, else from disk (checked; a corrupt or
        mismatched file is rebuilt with a warning), else ``build()``'s, stored in both (the
        file written atomically).
        """
        h = self.digest(kind, key)
        if h in self._mem:
            self._mem.move_to_end(h)
            self.hits += 1
            return self._mem[h]
        path = self.path(kind, key)
        with kept():  # shared by every later call, in any mode
            value = self._load(path, h) if path is not None and path.exists() else None
            if value is None:
                value = {k: torch.as_tensor(np.asarray(v)) for k, v in build().items()}
                self.builds += 1
                if path is not None:
                    self._save(path, h, value)
            else:
                self.hits += 1
        self._mem[h] = value
        while len(self._mem) > self.max_items:
            self._mem.popitem(last=False)
        return value

    def clear(self, disk: bool = False) -> None:
        """Empties the memory cache, and with ``disk=True`` deletes the cache's files too."""
        self._mem.clear()
        if disk and self.directory is not None and self.directory.exists():
            for p in self.directory.glob("*.npz"):
                p.unlink(missing_ok=True)

    def _load(self, path: Path, h: str) -> dict | None:
        try:
            with np.load(path, allow_pickle=False) as z:
                if str(z["__key__"]) != h:
                    raise ValueError("key mismatch")
                out = {k: torch.as_tensor(z[k]) for k in z.files if k != "__key__"}
            for k, v in out.items():
                if v.is_floating_point() and not torch.isfinite(v).all():
                    raise ValueError(f"non-finite values in '{k}'")
            return out
        except Exception as e:  # noqa: BLE001 - any failure means: do not trust the file
            warnings.warn(f"geometry cache file {path} is corrupt or stale ({e}); rebuilding it",
                          stacklevel=3)
            return None

    def _save(self, path: Path, h: str, value: dict) -> None:
        try:
            atomic_write(path, lambda f: np.savez(f, __key__=np.array(h),
                                                  **{k: v.numpy() for k, v in value.items()}))
        except OSError as e:
            warnings.warn(f"could not write geometry cache {path} ({e}); continuing without it",
                          stacklevel=3)


_DEFAULT: GeometryCache | None = None


def default_cache() -> GeometryCache:
    """The process-wide cache (directory from ``$USF_GRAPH_CACHE`` at first use)."""
    global _DEFAULT
    if _DEFAULT is None:
        _DEFAULT = GeometryCache()
    return _DEFAULT
