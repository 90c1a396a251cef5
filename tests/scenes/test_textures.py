"""Textures: scikit-image's photographs as mipmaps, and lookups at a pixel's footprint."""

import numpy as np

from usf_graph.scenes.textures import SIZE, TEXTURES, mipmaps, num_textures, sample


def test_mipmaps_halve_by_box_filtering_down_to_4_texels_and_keep_mean_1():
    levels = mipmaps()
    assert num_textures() == len(TEXTURES) == 15
    assert [lv.shape for lv in levels] == [(15, SIZE >> k, SIZE >> k, 3) for k in range(7)]
    np.testing.assert_allclose(levels[0].mean((1, 2, 3)), 1.0, rtol=1e-4)  # a tint's brightness kept
    for fine, coarse in zip(levels, levels[1:]):
        want = fine.reshape(15, len(coarse[0]), 2, len(coarse[0]), 2, 3).mean((2, 4))
        np.testing.assert_allclose(coarse, want, rtol=1e-5, atol=1e-6)
    assert (levels[0].min() >= 0) and levels[0].std() > 0.1  # photographs, not flat colours


def test_sample_reads_the_texel_under_uv_at_the_level_of_the_footprint():
    levels = mipmaps()
    rng = np.random.default_rng(0)
    tex = rng.integers(0, 15, 200)
    uv = rng.uniform(-3, 3, (200, 2))
    for footprint, lv in ((0.2 / SIZE, 0), (1.0 / SIZE, 0), (2.5 / SIZE, 1), (3.9 / SIZE, 1),
                          (16.0 / SIZE, 4), (1.0, 6), (50.0, 6)):
        got = sample(tex, uv, np.full(200, footprint))
        n = SIZE >> lv
        col, row = (np.floor((uv % 1.0) * n).astype(int) % n).T  # u across, v down
        np.testing.assert_array_equal(got, levels[lv][tex, row, col], err_msg=str(footprint))
    # whole repeats wrap; a per-point footprint picks a level per point
    np.testing.assert_array_equal(sample(tex, uv + [2.0, -1.0], np.full(200, 0.5 / SIZE)),
                                  sample(tex, uv, np.full(200, 0.5 / SIZE)))
    mixed = np.where(np.arange(200) % 2, 0.5 / SIZE, 4.0 / SIZE)
    got = sample(tex, uv, mixed)
    np.testing.assert_array_equal(got[1::2], sample(tex[1::2], uv[1::2], mixed[1::2]))
    np.testing.assert_array_equal(got[::2], sample(tex[::2], uv[::2], np.full(100, 4.0 / SIZE)))
    assert not np.array_equal(got[::2], sample(tex[::2], uv[::2], np.full(100, 0.5 / SIZE)))
