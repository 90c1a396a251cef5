"""SignCheck: the score against its definition, the flips, the field-of-view gate,
equivariance in float64, and how it attaches to a model's up estimate."""

import math

import numpy as np
import pytest
import torch

from usf_graph.models import SignCheck, SphericalUNet, set_sign_check
from usf_graph.testing import symmetry_permutation

from .test_gravity import _cap, _vertex_rotation


def _check(**kw) -> SignCheck:
    torch.manual_seed(0)
    return SignCheck(level=3, channels=(4, 4, 4), **kw).double().eval()


def _views(n: int, seed: int, points: int = 642):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, points, 3, dtype=torch.float64, generator=g)
    up = torch.nn.functional.normalize(torch.randn(n, 3, dtype=torch.float64, generator=g), dim=-1)
    return x, up


def test_score_is_the_area_weighted_mean_output_over_the_visible_points():
    check = _check()
    x, up = _views(3, 1)
    pos = check.net.backbone.grids[3].pos.double()
    mask = _cap(pos, [0.2, 1.0, 0.1], 100)
    with torch.no_grad():
        out = check.net(x, mask, up=up)[..., 0].numpy()
        got = check.score(x, mask, up).numpy()
        whole = check.score(x, None, up).numpy()
    w = check.area.numpy() * mask.numpy()
    np.testing.assert_allclose(got, (out * w).sum(-1) / w.sum(), rtol=0, atol=1e-12)
    with torch.no_grad():
        out = check.net(x, None, up=up)[..., 0].numpy()
    a = check.area.numpy()
    np.testing.assert_allclose(whole, (out * a).sum(-1) / a.sum(), rtol=0, atol=1e-12)


def test_the_checks_own_up_estimate_is_frozen():
    """The U-Net is handed its candidate up and never asks its own estimate, so training the
    check leaves that estimate alone; everything else trains."""
    params = list(_check().named_parameters())
    names = [n for n, p in params if p.requires_grad]
    frozen = [n for n, p in params if not p.requires_grad]
    assert frozen and all(n.startswith("net.gravity.") for n in frozen)
    assert names and not any(n.startswith("net.gravity.") for n in names)


def test_forward_flips_exactly_where_down_scores_higher():
    check = _check()
    x, up = _views(8, 2)
    with torch.no_grad():
        flip = check.score(x, None, -up) > check.score(x, None, up)
        got = check(x, None, up)
    assert 0 < int(flip.sum()) < len(up)  # both outcomes occur here
    torch.testing.assert_close(got[flip], -up[flip], rtol=0, atol=0)
    torch.testing.assert_close(got[~flip], up[~flip], rtol=0, atol=0)


def test_narrow_fields_of_view_are_not_asked():
    """A 40-degree cap (12% of the sphere) is below the 0.4 gate: the estimate passes
    unchanged even where the check would flip it; a 100-degree cap (59%) is asked."""
    check = _check()
    x, up = _views(8, 2)
    pos = check.net.backbone.grids[3].pos.double()
    narrow, wide = _cap(pos, [1.0, 0, 0], 40), _cap(pos, [1.0, 0, 0], 100)
    assert not check.asked(narrow) and check.asked(wide) and check.asked(None)
    with torch.no_grad():
        assert (check.score(x, narrow, -up) > check.score(x, narrow, up)).any()
        assert check(x, narrow, up) is up
        flip = check.score(x, wide, -up) > check.score(x, wide, up)
        torch.testing.assert_close(check(x, wide, up), torch.where(flip[:, None], -up, up))
    assert _check(min_field=0.0).asked(narrow)
    assert not _check(min_field=1.0).asked(narrow)  # both ends of [0, 1] are shares
    assert _check(min_field=1.0).asked(torch.ones(len(pos), dtype=torch.bool))  # at least the share
    for bad in (-0.1, 1.5):
        with pytest.raises(ValueError, match="min_field is a share of the sphere"):
            SignCheck(level=3, channels=(4, 4, 4), min_field=bad)


def test_the_check_rotates_with_the_input():
    check = _check(min_field=0.0)
    pos = check.net.backbone.grids[3].pos.double()
    R = _vertex_rotation(pos[5], turns=1)
    perm = symmetry_permutation(pos, R)
    x, up = _views(4, 3)
    mask = _cap(pos, [0.4, -0.3, 1.0], 80)
    xr, mr = torch.empty_like(x), torch.empty_like(mask)
    xr[:, perm], mr[perm] = x, mask
    with torch.no_grad():
        torch.testing.assert_close(check.score(xr, mr, up @ R.T), check.score(x, mask, up),
                                   rtol=0, atol=1e-9)
        torch.testing.assert_close(check(xr, mr, up @ R.T), check(x, mask, up) @ R.T,
                                   rtol=0, atol=1e-9)


def test_set_sign_check_passes_the_estimate_through_it_at_test_time_only():
    torch.manual_seed(1)
    seg = SphericalUNet(num_classes=3, level=3, channels=(4, 4), gravity=True).double().eval()
    keys = set(seg.state_dict())
    check = _check(min_field=0.0)
    x, _ = _views(8, 4)
    with torch.no_grad():
        free = seg.gravity(x)["up"]
        assert set_sign_check(seg, check) == 1 and seg.gravity.sign_check is check
        got = seg.gravity(x)["up"]
        torch.testing.assert_close(got, check(x, None, free), rtol=0, atol=0)
        assert not torch.equal(got, free)  # it flipped some here
        seg.gravity.train()  # training reads the head's scores: no polish, no check
        trained = seg.gravity(x)["up"]
        seg.gravity.set_sign_check(None)
        torch.testing.assert_close(seg.gravity(x)["up"], trained, rtol=0, atol=0)
        seg.gravity.set_sign_check(check)
        seg.gravity.eval()
    assert set(seg.state_dict()) == keys  # a test-time setting, not a weight
    fine = seg.refined(1)
    assert fine.gravity.sign_check.config["refine"] == 1
    assert len(fine.gravity.sign_check.area) == len(fine.gravity.view_pos) == 2562
    with pytest.raises(ValueError, match="the sign check reads 642 points"):
        fine.gravity.set_sign_check(check)
    with pytest.raises(TypeError, match="must be a SignCheck"):
        set_sign_check(seg, torch.nn.Linear(2, 2))
    assert set_sign_check(seg, None) == 1 and seg.gravity.sign_check is None
    assert set_sign_check(torch.nn.Linear(2, 2), check) == 0


def test_refined_keeps_the_weights_and_repr_names_the_settings():
    check = _check(min_field=0.3)
    fine = check.refined()  # one level finer by default
    assert all(torch.equal(a, b) for a, b in zip(check.state_dict().values(), fine.state_dict().values()))
    assert repr(fine) == "SignCheck(level=3, channels=[4, 4, 4], min_field=0.3, refine=1)"
    assert math.isclose(float(fine.area.sum()), 4 * math.pi, rel_tol=1e-9)
