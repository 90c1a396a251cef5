"""The three lenses of the benchmark protocols: a panorama, a 190-degree fisheye and a
90-degree pinhole."""

from __future__ import annotations

import math

from ..cameras import Camera, Equirectangular, KannalaBrandt, Pinhole


def protocol_cameras(size: int = 512) -> dict[str, Camera]:
    """``{"equirectangular": 2*size x size, "fisheye190": size x size equidistant
    Kannala-Brandt whose 190-degree circle touches the image sides, "pinhole90": size x
    size with a 90-degree horizontal field of view}``, all looking forward (+x)."""
    c = (size - 1) / 2
    f_fish = (size / 2) / math.radians(95)
    f_pin = (size / 2) / math.tan(math.radians(45))
    return {"equirectangular": Equirectangular(2 * size, size),
            "fisheye190": KannalaBrandt(f_fish, f_fish, c, c, size, size, k=(0.0, 0.0, 0.0, 0.0)).with_fov(190),
            "pinhole90": Pinhole(f_pin, f_pin, c, c, size, size)}
