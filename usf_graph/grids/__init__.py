"""Near-uniform sampling grids on S2: icosahedral, HEALPix, Fibonacci, equiangular."""

from .base import Grid, voronoi_areas
from .fibonacci import equiangular, fibonacci
from .healpix import healpix, locality_order
from .icosahedral import icosahedral, icosahedral_faces

_BUILDERS = {"icosahedral": icosahedral, "healpix": healpix, "fibonacci": fibonacci,
             "equiangular": equiangular}


def from_spec(spec: str) -> Grid:
    """Build a grid from a string: ``icosahedral:6``, ``healpix:64``, ``healpix:64,ring``,
    ``fibonacci:10000`` or ``equiangular:64,128``."""
    name, _, args = spec.partition(":")
    if name not in _BUILDERS:
        raise ValueError(f"unknown grid '{name}' in {spec!r}; use one of {sorted(_BUILDERS)}")
    vals = [a.strip() for a in args.split(",") if a.strip()]
    if name == "healpix":
        nest = not (len(vals) > 1 and vals[1].lower() in ("ring", "false"))
        return healpix(int(vals[0]), nest=nest)
    try:
        return _BUILDERS[name](*(int(v) for v in vals))
    except (TypeError, ValueError) as e:
        raise ValueError(f"bad grid spec {spec!r}: {e}") from e


__all__ = ["Grid", "icosahedral", "icosahedral_faces", "healpix", "fibonacci", "equiangular",
           "from_spec", "voronoi_areas", "locality_order"]
