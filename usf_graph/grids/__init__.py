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
    try:
        if name == "healpix":
            order = vals[1].lower() if len(vals) > 1 else "nest"
            orders = {"nest": True, "nested": True, "true": True, "ring": False, "false": False}
            if order not in orders or len(vals) > 2:  # a typo must not pick an ordering
                raise ValueError("HEALPix takes healpix:NSIDE, healpix:NSIDE,nest or "
                                 f"healpix:NSIDE,ring, not {args!r}")
            return healpix(*(int(v) for v in vals[:1]), nest=orders[order])
        return _BUILDERS[name](*(int(v) for v in vals))
    except (TypeError, ValueError) as e:
        raise ValueError(f"bad grid spec {spec!r}: {e}") from e


__all__ = ["Grid", "icosahedral", "icosahedral_faces", "healpix", "fibonacci", "equiangular",
           "from_spec", "voronoi_areas", "locality_order"]
