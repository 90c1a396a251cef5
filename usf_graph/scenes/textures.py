"""Surface textures from the photographs that scikit-image ships in its wheel, as mipmaps.

Only images bundled with ``skimage.data`` are used (no download on first use), resized to
256 x 256 and prefiltered into a pyramid, so a lookup at a pixel's footprint does not alias.
"""

from __future__ import annotations

import functools

import numpy as np

#: The ``skimage.data`` images used as textures (all bundled in the scikit-image wheel).
TEXTURES = ("brick", "grass", "gravel", "coffee", "rocket", "chelsea", "astronaut", "camera",
            "moon", "page", "text", "coins", "hubble_deep_field", "retina", "immunohistochemistry")
SIZE = 256


def num_textures() -> int:
    return len(TEXTURES)


@functools.lru_cache(maxsize=1)
def mipmaps() -> list[np.ndarray]:
    """Level ``l`` is ``[T, 256 / 2**l, 256 / 2**l, 3]`` float32 in [0, 1], each texture
    scaled to mean 1 so it modulates a tint without changing its brightness on average."""
    import cv2
    from skimage import data

    base = []
    for name in TEXTURES:
        img = np.asarray(getattr(data, name)(), np.float32)
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, -1)
        img = cv2.resize(img[..., :3], (SIZE, SIZE), interpolation=cv2.INTER_AREA)
        base.append(img / max(float(img.mean()), 1e-6))
    levels = [np.stack(base)]
    while levels[-1].shape[1] > 4:
        t = levels[-1]
        levels.append(0.25 * (t[:, ::2, ::2] + t[:, 1::2, ::2] + t[:, ::2, 1::2] + t[:, 1::2, 1::2]))
    return levels


def sample(tex_id: np.ndarray, uv: np.ndarray, footprint: np.ndarray) -> np.ndarray:
    """Texels ``[M, 3]`` of textures ``tex_id [M]`` at coordinates ``uv [M, 2]`` (in texture
    repeats) for pixels that cover ``footprint [M]`` repeats: the mip level whose texels
    are about one pixel."""
    levels = mipmaps()
    level = np.clip(np.floor(np.log2(np.maximum(footprint * SIZE, 1.0))), 0, len(levels) - 1)
    out = np.empty((len(tex_id), 3), np.float32)
    for lv in np.unique(level).astype(int):
        sel = level == lv
        t = levels[lv]
        n = t.shape[1]
        ij = np.floor(np.mod(uv[sel], 1.0) * n).astype(np.int64) % n
        out[sel] = t[tex_id[sel], ij[:, 1], ij[:, 0]]
    return out
