"""The sign check's training and loading (train.sign)."""

import pytest
import torch
from torch import nn

from usf_graph.grids import icosahedral
from usf_graph.nn import MaskedBatchNorm
from usf_graph.train.sign import load_sign_check, pretrain_sign


class _SignViews:
    """Views whose first channel is each point's height along the view's gravity: an
    image that says which way is up, for the sign check to learn."""

    def __init__(self, n: int, seed: int, level: int = 3):
        gen = torch.Generator().manual_seed(seed)
        self.grid = icosahedral(level)
        pos = self.grid.pos.float()
        self.gravity = nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=-1)
        noise = 0.3 * torch.randn(n, len(pos), 2, generator=gen)
        self.x = torch.cat([(pos @ self.gravity.T).T[..., None], noise], -1)
        self.mask = torch.ones(n, len(pos), dtype=torch.bool)

    def __len__(self):
        return len(self.x)


def _sign_check():
    from usf_graph.models import SignCheck

    torch.manual_seed(0)
    return SignCheck(level=3, channels=(8, 8, 8))


def test_pretrain_sign_learns_which_way_is_up():
    """Untrained, the check flips about half of the right ups of new views; trained on
    views whose image shows the height, it keeps every right up and turns every
    upside-down one."""
    test = _SignViews(16, 1)
    x, g = test.x, test.gravity
    check = _sign_check().eval()
    with torch.no_grad():
        before = (check(x, None, g) == g).all(-1).float().mean()
    check = pretrain_sign(check, _SignViews(48, 0), epochs=3, cut_epochs=1, share=0.5, progress=False)
    assert not check.training
    with torch.no_grad():
        kept, turned = check(x, None, g), check(x, None, -g)
    assert torch.equal(kept, g) and torch.equal(turned, g), float(before)


def test_pretrain_sign_runs_its_two_phases_as_documented(monkeypatch):
    """First whole views at ``lr[0]`` with the normalizations training, then cut views at
    ``lr[1]`` with them frozen; each phase's cosine schedule spans its own steps."""
    made = []

    class Adam(torch.optim.Adam):
        def __init__(self, params, lr):
            made.append({"lr": lr})
            super().__init__(params, lr=lr)

    class Cosine(torch.optim.lr_scheduler.CosineAnnealingLR):
        def __init__(self, opt, T_max):
            made[-1]["T_max"] = T_max
            super().__init__(opt, T_max)

    monkeypatch.setattr(torch.optim, "Adam", Adam)
    monkeypatch.setattr(torch.optim.lr_scheduler, "CosineAnnealingLR", Cosine)
    check, calls = _sign_check(), []
    norm, score = next(m for m in check.modules() if isinstance(m, MaskedBatchNorm)), check.score

    def spy(x, mask, up):
        calls.append((len(made), mask is None or bool(mask.all()), norm.training))
        return score(x, mask, up)

    monkeypatch.setattr(check, "score", spy)
    pretrain_sign(check, _SignViews(10, 0), epochs=2, cut_epochs=1, share=1.0, batch_size=4,
                  lr=(0.01, 0.002), progress=False)
    assert made == [{"lr": 0.01, "T_max": 6}, {"lr": 0.002, "T_max": 3}]  # 3 batches an epoch
    assert [c[1:] for c in calls if c[0] == 1] == [(True, True)] * 12  # 2 scores a batch
    assert [c[1:] for c in calls if c[0] == 2] == [(False, False)] * 6


def test_pretrain_sign_refuses_other_grids_and_nan_views():
    with pytest.raises(ValueError, match="the views have 2562 points, the sign check reads 642"):
        pretrain_sign(_sign_check(), _SignViews(4, 0, level=4), progress=False)
    bad = _SignViews(8, 0)
    bad.x[3, 10, 0] = float("nan")
    with pytest.raises(ValueError, match="x has NaN or inf"):
        pretrain_sign(_sign_check(), bad, epochs=1, cut_epochs=0, progress=False)
    bad.x = torch.full_like(bad.x, 3e38)  # finite views whose loss overflows
    with pytest.raises(FloatingPointError, match="sign check's loss is not finite"):
        pretrain_sign(_sign_check(), bad, epochs=1, cut_epochs=0, progress=False)


def test_a_saved_sign_check_loads_with_its_weights(tmp_path):
    from usf_graph.train.engine import save_checkpoint

    check = _sign_check()
    check.config["min_field"] = 0.25
    save_checkpoint(tmp_path / "sign.pt", check, {"model": "sign_check", **check.config}, {})
    got = load_sign_check(tmp_path / "sign.pt")
    assert not got.training and got.config == check.config
    assert all(torch.equal(a, b) for a, b in zip(got.state_dict().values(), check.state_dict().values()))
    save_checkpoint(tmp_path / "other.pt", check, {"model": "spherical_unet"}, {})
    with pytest.raises(ValueError, match="is not a sign check"):
        load_sign_check(tmp_path / "other.pt")


def test_jittered_turns_each_up_by_a_uniform_angle_about_an_orthogonal_axis():
    import math

    from usf_graph.train.sign import jittered

    gen = torch.Generator().manual_seed(0)
    g = nn.functional.normalize(torch.randn(4000, 3, generator=gen, dtype=torch.float64), dim=-1)
    j = jittered(g, 8.0, gen)
    torch.testing.assert_close(j.norm(dim=-1), torch.ones(4000, dtype=torch.float64))
    angle = torch.rad2deg(torch.acos((g * j).sum(-1).clamp(max=1)))
    assert angle.max() <= 8.0 + 1e-9 and angle.max() > 7.9 and angle.min() < 0.1
    assert abs(float(angle.mean()) - 4.0) < 0.15  # uniform in [0, 8]: mean 4, sd 2.3 / sqrt(4000)
    # the axes: orthogonal to g and spread evenly around it
    axis = nn.functional.normalize(torch.linalg.cross(g, j), dim=-1)
    assert (axis * g).sum(-1).abs().max() < 1e-9
    side = nn.functional.normalize(j - (j * g).sum(-1, keepdim=True) * g, dim=-1)
    e1 = nn.functional.normalize(torch.linalg.cross(g, torch.tensor([[0.0, 0.0, 1.0]]).double().expand_as(g)), dim=-1)
    turn = torch.atan2((torch.linalg.cross(e1, side) * g).sum(-1), (e1 * side).sum(-1))
    counts = torch.histc(turn, bins=4, min=-math.pi, max=math.pi)
    assert (counts > 850).all() and (counts < 1150).all(), counts
    assert torch.equal(jittered(g, 0.0, gen), g)
