"""From images to spherical graphs: interpolation tables, field of view, cache, rendering,
rigs, and lifted samples on disk.

The names below load their module on first use, so that a light submodule (``choices``)
does not import torch and PyG with the rest.
"""

import importlib

_WHERE = {"GeometryCache": "cache", "default_cache": "cache",
          "SphericalFrontend": "frontend", "default_radius": "frontend", "grid_graph": "frontend",
          "load_lifted": "lifted", "read_lifted": "lifted", "save_lifted": "lifted",
          "Reimager": "reimage", "render": "reimage",
          "RigFrontend": "rig", "RigReimager": "rig", "blend_weights": "rig",
          "choose_distance": "rig", "render_rig": "rig"}

__all__ = list(_WHERE)


def __getattr__(name: str):
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
    globals()[name] = value  # loaded once; tools that read the module's dict (pdoc) see it
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
