"""Random fields of view: caps and pinhole frusta of the asked sizes, reproducible."""

import math

import numpy as np
import pytest
import torch

from usf_graph import grids
from usf_graph.train.fov import (
    RandomFields,
    random_cap,
    random_field_of_view,
    random_frustum,
    random_pinhole,
)


def _gen(seed):
    return torch.Generator().manual_seed(seed)


def test_random_cap_is_a_cap_of_the_asked_size():
    pos = grids.icosahedral(4).pos.double()
    for seed in range(5):
        m = random_cap(pos, 45, 100, generator=_gen(seed))
        assert torch.equal(m, random_cap(pos, 45, 100, generator=_gen(seed)))
        # a cap: the seen points are those nearest its centre (their mean direction)
        c = torch.nn.functional.normalize(pos[m].mean(0), dim=0)
        d = pos @ c
        assert d[m].min() > d[~m].max() - 1e-2
        # of a size between the two radii (area fraction (1 - cos r) / 2)
        frac = m.double().mean()
        assert 0.146 - 0.01 < frac < 0.587 + 0.01


def test_random_frustum_is_what_its_pinhole_sees():
    g = grids.healpix(32)  # equal areas: the seen share of points is the solid angle's
    pos = g.pos.double()
    for seed in range(6):
        cam = random_pinhole(60, 120, generator=_gen(seed))
        m = random_frustum(pos, 60, 120, generator=_gen(seed))
        assert torch.equal(m, random_frustum(pos, 60, 120, generator=_gen(seed)))
        # the drawn fields of view, from the focal lengths, in range
        half = [math.atan(32 / f) for f in (cam.fx, cam.fy)]
        assert all(math.radians(30) <= h <= math.radians(60) for h in half)
        # solid angle of a rectangular pyramid: 4 asin(sin a sin b) for half-angles a, b
        omega = 4 * math.asin(math.sin(half[0]) * math.sin(half[1]))
        assert abs(4 * math.pi * m.double().mean() - omega) < 0.03 * omega
        # it looks along the camera's axis: the seen points surround it
        axis = torch.as_tensor(cam.rotation[:, 2])
        assert (pos[m] @ axis).min() > math.cos(math.atan(math.hypot(*map(math.tan, half)))) - 1e-9
        assert torch.nn.functional.normalize(pos[m].mean(0), dim=0) @ axis > 0.999


def test_random_field_of_view_draws_both_kinds():
    pos = grids.icosahedral(3).pos.double()
    gen = _gen(0)
    masks = [random_field_of_view(pos, gen) for _ in range(40)]
    fracs = torch.stack([m.double().mean() for m in masks])
    assert (fracs > 0.05).all() and (fracs < 0.6).all()
    # caps are rotation-symmetric about their centre; frusta have corners: both occur
    spread = []
    for m in masks:
        c = torch.nn.functional.normalize(pos[m].mean(0), dim=0)
        d = pos @ c
        spread.append(float(d[~m].max() - d[m].min()))  # < 0 only for a cap (up to the grid)
    assert min(spread) < 0.02 and max(spread) > 0.1


def test_random_fields_draw_a_share_within_a_mask():
    pos = grids.icosahedral(3).pos.double()
    draws = RandomFields(pos, share=0.3, seed=1)
    got = [draws() for _ in range(300)]
    cut = [m for m in got if m is not None]
    assert 0.22 < len(cut) / len(got) < 0.38  # the share of cut batches
    assert len({m.numpy().tobytes() for m in cut}) == len(cut)  # each a new field of view
    # the same seed, the same draws
    again = RandomFields(pos, share=0.3, seed=1)
    assert all((a is None and b is None) or torch.equal(a, b)
               for a, b in zip(got[:50], (again() for _ in range(50))))
    # within a camera's mask; a mask they never meet leaves the batch whole
    half = pos[:, 2] > 0
    inside = RandomFields(pos, share=1.0, seed=2)
    for _ in range(20):
        m = inside(half)
        assert m is None or not (m & ~half).any()
    one = torch.zeros(len(pos), dtype=torch.bool)
    one[0] = True
    assert sum(inside(one) is None for _ in range(20)) > 10
    assert RandomFields(pos, share=0.0)(half) is None
    for bad in (-0.1, 1.1):
        with pytest.raises(ValueError, match="share"):
            RandomFields(pos, share=bad)
    with pytest.raises(ValueError, match="points"):
        RandomFields(pos[:, :2], share=0.5)


def test_camera_field_turns_the_lens_about_gravity():
    """A level 90-degree pinhole turned by ``yaw`` stays level, its centre on the horizon
    at a new azimuth each draw; a tilted one keeps its tilt; ``so3`` mounts it anywhere.
    Always exactly its field of view: the solid angle 4 asin(sin a sin b) of its frustum."""
    from usf_graph.scenes.lenses import protocol_cameras
    from usf_graph.train.fov import camera_field

    g = grids.healpix(32)
    pos = g.pos.double()
    cam = protocol_cameras(64)["pinhole90"]
    omega = 4 * math.asin(math.sin(math.pi / 4) ** 2)
    gen = _gen(0)
    centres = []
    for _ in range(12):
        m = camera_field(cam, pos, "yaw", gen)
        assert abs(4 * math.pi * m.double().mean() - omega) < 0.03 * omega
        c = torch.nn.functional.normalize(pos[m].mean(0), dim=0)
        assert abs(c[2]) < 0.01  # level: as much above the horizon as below
        assert abs(pos[m][:, 2].max() + pos[m][:, 2].min()) < 0.03
        centres.append(float(torch.atan2(c[1], c[0])))
    assert len({round(a, 3) for a in centres}) == 12 and max(centres) - min(centres) > 3
    # looking 30 degrees up (the camera pitched about the sphere's y axis): it stays so
    t = math.radians(30)
    pitch = torch.tensor([[math.cos(t), 0, -math.sin(t)], [0, 1, 0], [math.sin(t), 0, math.cos(t)]],
                         dtype=torch.float64).numpy()
    up30 = cam.with_rotation(pitch @ cam.rotation)
    for _ in range(4):
        m = camera_field(up30, pos, "yaw", gen)
        c = torch.nn.functional.normalize(pos[m].mean(0), dim=0)
        assert abs(float(c[2]) - math.sin(t)) < 0.03
    heights = [float(torch.nn.functional.normalize(pos[m].mean(0), dim=0)[2])
               for m in (camera_field(cam, pos, "so3", gen) for _ in range(30))]
    assert max(abs(h) for h in heights) > 0.5
    with pytest.raises(ValueError, match="turn"):
        camera_field(cam, pos, "roll", gen)
    with pytest.raises(ValueError, match="turn"):
        RandomFields(pos, 0.5, camera=cam, turn="roll")


def test_random_fields_through_a_camera_draw_its_turned_field():
    """With ``camera`` every cut is :func:`camera_field`'s draw from the same generator,
    after the draw that decides whether to cut."""
    from usf_graph.scenes.lenses import protocol_cameras
    from usf_graph.train.fov import camera_field

    pos = grids.icosahedral(3).pos.double()
    cam = protocol_cameras(32)["fisheye190"]
    draws = RandomFields(pos, share=1.0, seed=5, camera=cam)
    gen = _gen(5)
    for _ in range(5):
        torch.rand((), generator=gen)
        assert torch.equal(draws(), camera_field(cam, pos, "yaw", gen))


def test_default_ranges_measured_from_what_is_drawn(monkeypatch):
    """Defaults: pinholes of 60 to 120 degrees each way (measured between the rays of the
    image's outer edges, each axis drawn on its own), caps of 45 to 100 degrees (from the
    area they cover), and frusta and caps with equal odds."""
    from usf_graph.train import fov

    gen, fovs = _gen(1), []
    for _ in range(40):
        cam = random_pinhole(generator=gen)
        c = (cam.width - 1) / 2
        rays = cam.unproject(np.array([[-0.5, c], [cam.width - 0.5, c], [c, -0.5], [c, cam.height - 0.5]]))[0]
        fovs.append([math.degrees(math.acos(rays[0] @ rays[1])), math.degrees(math.acos(rays[2] @ rays[3]))])
    fovs = np.array(fovs)
    assert fovs.min() > 60 - 1e-6 and fovs.max() < 120 + 1e-6 and fovs.min() < 66 and fovs.max() > 114
    assert np.abs(fovs[:, 0] - fovs[:, 1]).mean() > 10
    pos = grids.healpix(16).pos.double()
    radii = [math.degrees(math.acos(1 - 2 * float(random_cap(pos, generator=gen).double().mean())))
             for _ in range(40)]
    assert 44 < min(radii) < 52 and 93 < max(radii) < 101
    omega = [4 * math.pi * float(random_frustum(pos, generator=gen).double().mean()) for _ in range(40)]
    assert 0.9 < min(omega) < 1.5 and 2.6 < max(omega) < 3.6  # 60 x 60: 1.0 sr; 120 x 120: 3.4
    kinds, real = [], fov.random_frustum
    monkeypatch.setattr(fov, "random_frustum", lambda *a, **k: kinds.append(1) or real(*a, **k))
    for _ in range(400):
        random_field_of_view(grids.icosahedral(1).pos.double(), gen)
    assert 0.42 < len(kinds) / 400 < 0.58
