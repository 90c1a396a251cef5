"""The segmentation protocol end to end on a few tiny rooms (through PyG batches), the loss,
checkpoints read back by ``eval seg``, and the Stanford 2D-3D-S command on fixtures."""

import json
from types import SimpleNamespace

import pytest
import torch
from torch_geometric.loader import DataLoader

from usf_graph.cli import main
from usf_graph.models import SphericalUNet
from usf_graph.scenes import IGNORE
from usf_graph.train.checkpoints import load_protocol_model
from usf_graph.train.fov import camera_field
from usf_graph.train.gravity import UP_JITTER, UP_WEIGHT, pretrain_up, trains_up
from usf_graph.train.seg import (
    MODELS,
    ThroughRandomFields,
    balanced_weights,
    format_table,
    make_model,
    protocol_sets,
    run,
    segmentation_loss,
    segmentation_step,
    split_batch,
)
from usf_graph.train.seg_eval import PROTOCOL


def test_loss_ignores_and_weights():
    torch.manual_seed(0)
    logits = torch.randn(2, 5, 3, dtype=torch.float64)
    target = torch.tensor([[0, 1, 255, 2, 1], [2, 255, 0, 0, 1]])
    keep = target != 255
    lp = torch.log_softmax(logits, -1)
    nll = -lp.gather(-1, target.clamp(max=2)[..., None])[..., 0]
    assert torch.allclose(segmentation_loss(logits, target), nll[keep].mean())
    cw, pw = torch.tensor([1.0, 2.0, 0.5]), torch.rand(5, dtype=torch.float64)
    w = cw.double()[target.clamp(max=2)] * pw * keep
    assert torch.allclose(segmentation_loss(logits, target, class_weight=cw, point_weight=pw),
                          (nll * w).sum() / w.sum())
    # the pixel layout [B, C, H, W] gives the same numbers
    assert torch.allclose(segmentation_loss(logits.transpose(1, 2)[..., None], target[..., None]),
                          nll[keep].mean())
    with pytest.raises(ValueError, match="NaN"):
        segmentation_loss(torch.full((1, 2, 3), float("nan")), torch.zeros(1, 2, dtype=torch.long))
    for bad in (3, -1, 254):  # 13 Stanford classes into a 3-class model, say
        with pytest.raises(ValueError, match=rf"class indices in \[0, 3\) or 255 .*found \[{bad}\]"):
            segmentation_loss(logits, torch.where(target == 1, bad, target))


def test_protocol_runs_and_scores_every_test(tmp_path, capsys):
    res = run(root=tmp_path / "rooms", out=tmp_path / "out", size=32, level=3, num_train=3,
              num_test=2, epochs=1, batch_size=2, progress=False, up_extra=2, up_caps=0.5,
              fov_epochs=1)
    saved = json.loads((tmp_path / "out" / "results.json").read_text())
    assert saved["up_extra"] == 2 and saved["up_caps"] == 0.5  # cheap views on the protocol's grid
    assert saved["fov_epochs"] == 1
    for name in ("spherical_unet", "spherical_deeplab", "planar_unet"):  # every model's second phase
        log = json.loads((tmp_path / "out" / name / "second_phase" / "metrics.json").read_text())
        assert [r["epoch"] for r in log] == [1]
    # the DeepLab's oriented kernels on every level below the input's, the U-Net's none
    configs = {n: torch.load(tmp_path / "out" / f"{n}.pt", weights_only=True)["config"]
               for n in ("spherical_unet", "spherical_deeplab")}
    assert configs["spherical_deeplab"]["upright_convs"] == 2
    assert configs["spherical_unet"]["upright_convs"] is None
    assert len(list((tmp_path / "rooms" / "processed").glob("rooms_gravity_*.pt"))) == 1
    for name in ("spherical_unet", "spherical_deeplab", "planar_unet"):
        for k in PROTOCOL:
            r = saved[name][k]
            assert 0 <= r["mIoU"] <= 1 and 0 <= r["mAcc"] <= 1
            assert ("sphere_mIoU" in r) == name.startswith("spherical")
            assert ("up" in r) == name.startswith("spherical")  # its estimate's report
            if "up" in r:
                assert r["up"]["views"] == 2 and 0 <= r["up"]["median_err_deg"] <= 180
        assert (tmp_path / "out" / f"{name}.pt").is_file()
    assert (tmp_path / "out" / "seg_results.png").is_file()
    assert "(e) finer grid" in format_table(res) and "| planar_unet |" in format_table(res)
    # resuming the finished run from the shell loads every stage (the up estimate's, both
    # phases), scores the same models again, to the digit, and prints their table and targets
    capsys.readouterr()
    assert main(["train", "seg", "--root", str(tmp_path / "rooms"), "--out", str(tmp_path / "out"),
                 "--size", "32", "--level", "3", "--num-train", "3", "--num-test", "2",
                 "--epochs", "1", "--batch-size", "2", "--up-extra", "2", "--up-caps", "0.5",
                 "--fov-epochs", "1", "--resume"]) == 0
    again = json.loads((tmp_path / "out" / "results.json").read_text())
    for name in ("spherical_unet", "spherical_deeplab", "planar_unet"):
        assert again[name] == saved[name]
    out = capsys.readouterr().out
    assert "Segmentation on procedural rooms, trained on upright panoramas (3 views; 2 test" in out
    # its clock counts this invocation only, and says so
    assert not saved["resumed"] and again["resumed"]
    assert f"test views each; {again['seconds']} s since --resume)" in out
    assert f"mIoU (camera pixels):\n{format_table(res, 'mIoU')}" in out
    assert f"mAcc (camera pixels):\n{format_table(res, 'mAcc')}" in out
    assert "The issue's targets (bold: misses):" in out and "pinhole" in out
    assert f"figure: {res['figure']}" in out
    assert main(["eval", "seg", str(tmp_path / "out" / "spherical_unet.pt"), "--root",
                 str(tmp_path / "rooms"), "--num-test", "2", "--test", "b", "e"]) == 0
    out = capsys.readouterr().out
    for k in ("b", "e"):
        assert f"({k}) mIoU {100 * saved['spherical_unet'][k]['mIoU']:.2f}" in out
        up = saved["spherical_unet"][k]["up"]
        assert f"({k}) up estimate: median error {up['median_err_deg']:.1f} deg" in out
    # --render soft: other pixel labels from the same points (the sphere's score is theirs)
    assert main(["eval", "seg", str(tmp_path / "out" / "spherical_unet.pt"), "--root",
                 str(tmp_path / "rooms"), "--num-test", "2", "--test", "b", "--render", "soft"]) == 0
    assert f"sphere_mIoU {100 * saved['spherical_unet']['b']['sphere_mIoU']:.2f}" in \
        capsys.readouterr().out
    assert main(["eval", "seg", str(tmp_path / "out" / "planar_unet.pt"), "--root",
                 str(tmp_path / "rooms"), "--render", "soft"]) == 2
    assert "a planar model labels" in capsys.readouterr().err
    # the checkpoint knows its rooms' seed: eval scores the test rooms of that seed, and
    # refuses those of seed - 1, which are the rooms it trained on
    ckpt = str(tmp_path / "out" / "spherical_unet.pt")
    assert load_protocol_model(ckpt).seed == 0
    assert main(["eval", "seg", ckpt, "--root", str(tmp_path / "rooms"), "--seed", "-1"]) == 2
    assert "are the rooms" in capsys.readouterr().err
    blob = torch.load(ckpt, weights_only=True)
    del blob["data"]  # as saved before checkpoints recorded it
    torch.save(blob, tmp_path / "old.pt")
    assert main(["eval", "seg", str(tmp_path / "old.pt"), "--root", str(tmp_path / "rooms"),
                 "--num-test", "2", "--test", "a"]) == 0
    assert "does not record its training seed" in capsys.readouterr().out
    with pytest.raises(ValueError, match="extra panoramas"):  # before rendering anything
        run(root=tmp_path / "none", out=tmp_path / "none", seed=999, up_extra=2, progress=False)
    assert not (tmp_path / "none").exists()
    # --up-lines: the estimate picks among each image's straight lines' axes, every lens
    assert main(["eval", "seg", ckpt, "--root", str(tmp_path / "rooms"), "--num-test", "2",
                 "--test", "a", "d", "--up-lines"]) == 0
    out = capsys.readouterr().out
    assert "(a) up estimate" in out and "(d) up estimate" in out
    assert out.count("picked among straight-line axes on") == 2
    # --known-up: each view's true gravity instead of the estimate, the rotated ones too
    assert main(["eval", "seg", ckpt, "--root", str(tmp_path / "rooms"), "--num-test", "2",
                 "--test", "b", "c", "--known-up"]) == 0
    blob = torch.load(ckpt, weights_only=True)
    cfg = {k: v for k, v in blob["config"].items() if k not in ("model", "size")}
    net = SphericalUNet.from_config(cfg)
    net.load_state_dict(blob["state_dict"])
    ds = protocol_sets(tmp_path / "rooms", size=32, level=3, num_train=0, num_test=2,
                       tests=("c",), progress=False)["c"]
    # --level-prior: the fisheye's up estimate assumes a level camera; the report follows it
    from usf_graph.models import set_level_prior
    from usf_graph.train.gravity import up_report, views_up

    capsys.readouterr()
    assert main(["eval", "seg", ckpt, "--root", str(tmp_path / "rooms"), "--num-test", "2",
                 "--test", "c", "--level-prior", "50"]) == 0
    out = capsys.readouterr().out
    set_level_prior(net, 50)
    r = up_report(net.gravity, ds.x, ds.mask[0], views_up(ds))
    assert f"(c) up estimate: median error {r['median_err_deg']:.1f} deg" in out
    # --sign-check: a saved check passes the estimate on; the finer grid's (e) reads its refined copy
    from usf_graph.models import SignCheck, set_sign_check
    from usf_graph.train.engine import save_checkpoint

    torch.manual_seed(3)
    check = SignCheck(level=3, channels=(4, 4, 4), min_field=0.0)
    save_checkpoint(tmp_path / "sign.pt", check, {"model": "sign_check", **check.config}, {})
    assert main(["eval", "seg", ckpt, "--root", str(tmp_path / "rooms"), "--num-test", "2",
                 "--test", "c", "e", "--sign-check", str(tmp_path / "sign.pt")]) == 0
    out = capsys.readouterr().out
    set_level_prior(net, 0)
    set_sign_check(net, check.eval())
    r = up_report(net.gravity, ds.x, ds.mask[0], views_up(ds))
    assert f"(c) up estimate: median error {r['median_err_deg']:.1f} deg" in out and "(e) mIoU" in out
    # a planar model has no estimate to set either on
    for option, value in (("--level-prior", "1"), ("--sign-check", str(tmp_path / "sign.pt"))):
        assert main(["eval", "seg", str(tmp_path / "out" / "planar_unet.pt"), "--root",
                     str(tmp_path / "rooms"), "--num-test", "2", "--test", "c", option, value]) == 2
        assert f"{option} needs a spherical model" in capsys.readouterr().err


def test_a_planar_only_protocol_renders_no_views_for_an_up_estimate(tmp_path):
    run(root=tmp_path / "rooms", out=tmp_path / "out", size=32, level=3, num_train=2,
        num_test=1, epochs=1, batch_size=2, progress=False, models=("planar_unet",), up_extra=2)
    assert not list((tmp_path / "rooms" / "processed").glob("rooms_gravity_*.pt"))
    assert (tmp_path / "out" / "planar_unet.pt").is_file()


def test_pyg_batches_feed_both_model_kinds(tmp_path):
    sets = protocol_sets(tmp_path, size=32, level=3, num_train=0, num_test=2, tests=("c",),
                         progress=False)
    batch = next(iter(DataLoader(sets["c"], batch_size=2)))
    x, y, mask, image, label = split_batch(batch)
    ds = sets["c"]
    assert torch.equal(x, ds.x.float()) and torch.equal(y, ds.y)
    assert torch.equal(mask, ds.mask[0]) and 0 < mask.float().mean() < 0.7
    assert torch.equal(image, ds.image.permute(0, 3, 1, 2).float() / 255)  # [0, 1]
    assert torch.equal(label, ds.label_image.long())
    mixed = batch.clone()  # two cameras in one batch: refused, not read as the first's
    mixed.mask = batch.mask.clone()
    mixed.mask[-1] = ~mixed.mask[-1]
    with pytest.raises(ValueError, match="different fields of view; batch one camera"):
        split_batch(mixed)
    torch.manual_seed(0)
    m = SphericalUNet(level=3, channels=(8, 8, 8, 8))
    loss, stats, n = segmentation_step(m, batch)
    assert n == 2 and loss.item() > 0 and 0 <= stats["acc"] <= 1
    loss.backward()
    assert all(p.grad is not None for p in m.head.parameters())
    # with a gravity head: the decoder reads the jittered true up, the head's loss is added
    torch.manual_seed(0)
    g = SphericalUNet(level=3, channels=(8, 8, 8, 8), gravity=True)
    torch.manual_seed(5)
    loss_g, stats_g, _ = segmentation_step(g, batch)
    torch.manual_seed(5)
    z = torch.tensor([[0.0, 0, 1]] * 2)
    noisy = z + UP_JITTER * torch.randn(2, 3)
    logits, grav = g(x, mask, up=noisy, return_gravity=True)
    aux = g.gravity.head.loss(grav, z)
    torch.testing.assert_close(loss_g, segmentation_loss(logits, y) + UP_WEIGHT * aux)
    assert 0 <= stats_g["up_err_deg"] <= 180 and aux > 0
    loss_g.backward()
    assert all(p.grad is not None for p in g.gravity.parameters())
    # the network reads the given up, and without one the estimate
    g.eval()
    with torch.no_grad():
        est = g(x, mask, return_gravity=True)[1]["up"]
        assert not torch.allclose(g(x, mask, up=-est), g(x, mask))
        torch.testing.assert_close(g(x, mask), g(x, mask, up=est))
        # a given up spares the estimate in evaluation, unless it is asked for
        calls = []
        hook = g.gravity.register_forward_hook(lambda *a: calls.append(1))
        g(x, mask, up=est)
        assert calls == []
        assert g(x, mask, up=est, return_gravity=True)[1] is not None and calls == [1]
        hook.remove()
    with pytest.raises(ValueError, match="gravity=True"):
        m(x, mask, up=noisy)
    # a planar model reads the images and scores their labelled pixels
    from usf_graph.models import PlanarUNet

    p = PlanarUNet(13, channels=(8, 8, 8, 8))
    loss_p, stats_p, _ = segmentation_step(p, batch)
    with torch.no_grad():
        logits_p = p(image)
    keep = label != IGNORE
    torch.testing.assert_close(loss_p, segmentation_loss(logits_p, label))
    assert stats_p["acc"] == pytest.approx(
        (logits_p.argmax(1)[keep] == label[keep]).double().mean().item())
    # samples without images (a real dataset's points only): spherical models train, planar not
    bare = batch.clone()
    del bare.image
    assert segmentation_step(m, bare)[0].item() == pytest.approx(loss.item())
    with pytest.raises(ValueError, match="planar model trains on images"):
        segmentation_step(p, bare)
    # a batch with no labelled point (a field of view over ignored labels): 0, not NaN
    unlabelled = batch.clone()
    unlabelled.y = torch.full_like(batch.y, IGNORE)
    loss_u, stats_u, _ = segmentation_step(m, unlabelled)
    assert loss_u.item() == 0.0 and stats_u["acc"] == 0.0


def test_random_fields_of_view_cut_batches_and_ignore_their_labels_outside(tmp_path):
    sets = protocol_sets(tmp_path, size=32, level=3, num_train=0, num_test=3, tests=("a", "d"),
                         progress=False)
    ds, pos = sets["a"], sets["a"].grid.pos
    every, again = (ThroughRandomFields(pos, share=1.0, seed=4) for _ in range(2))
    whole = next(iter(DataLoader(ds, batch_size=3)))
    cuts = set()
    for _ in range(5):
        batch = every([ds[i] for i in range(3)])
        x, y, mask, _, _ = split_batch(batch)
        assert torch.equal(x, whole.x.view(3, -1, 3).float())  # the signal is kept
        assert mask.dtype == torch.bool and 0.05 < mask.float().mean() < 0.6
        # labels inside kept, outside ignored, in every sample
        assert torch.equal(y[:, mask], whole.y.view(3, -1)[:, mask])
        assert (y[:, ~mask] == IGNORE).all()
        assert torch.equal(mask, split_batch(again([ds[i] for i in range(3)]))[2])  # seeded
        cuts.add(int(mask.sum()))
    assert len(cuts) == 5  # a new field of view each batch
    kept = ThroughRandomFields(pos, share=0.0)([ds[0], ds[1]])
    assert torch.equal(kept.y, whole.y[:2 * len(pos)]) and bool(kept.mask.all())
    # within a camera's own field of view
    lens = sets["d"]
    mask = split_batch(ThroughRandomFields(pos, share=1.0)([lens[0], lens[1]]))[2]
    assert not (mask & ~lens.mask[0]).any()
    # through a given lens, turned about gravity: its field of view, labels outside ignored
    gen = torch.Generator().manual_seed(7)
    torch.rand((), generator=gen)
    batch = ThroughRandomFields(pos, 1.0, seed=7, camera=lens.camera)([ds[0], ds[1]])
    _, y, mask, _, _ = split_batch(batch)
    assert torch.equal(mask, camera_field(lens.camera, pos, "yaw", gen))
    assert (y[:, ~mask] == IGNORE).all() and torch.equal(y[:, mask], whole.y.view(3, -1)[:2, mask])
    with pytest.raises(ValueError, match="share"):
        ThroughRandomFields(pos, share=-0.1)
    with pytest.raises(ValueError, match="points"):
        ThroughRandomFields(pos[:10], share=1.0)([ds[0]])


def test_pretrained_up_estimate_is_frozen_and_spared_in_training(tmp_path):
    """pretrain_up trains the UpNet alone (its loss falls) and freezes it; the segmenter's
    step then reads the jittered known up, never runs the UpNet, and adds no up loss."""
    sets = protocol_sets(tmp_path, size=32, level=3, num_train=4, num_test=0, tests=(),
                         progress=False)
    torch.manual_seed(0)
    g = SphericalUNet(level=3, channels=(8, 8, 8, 8), gravity=True)
    before = {k: v.clone() for k, v in g.gravity.state_dict().items()}
    pretrain_up(g, sets["train"], epochs=3, batch_size=2, progress=False, log_dir=tmp_path / "up")
    hist = json.loads((tmp_path / "up" / "metrics.json").read_text())
    assert hist[-1]["train_loss"] < hist[0]["train_loss"]
    assert not torch.equal(before["head.score.weight"], g.gravity.state_dict()["head.score.weight"])
    assert not trains_up(g) and not any(p.requires_grad for p in g.gravity.parameters())
    batch = next(iter(DataLoader(sets["train"], batch_size=2)))
    x, y, mask, _, _ = split_batch(batch)
    w = torch.rand(13)
    g.train()
    calls = []
    hook = g.gravity.register_forward_hook(lambda *a: calls.append(1))
    torch.manual_seed(5)
    loss, stats, _ = segmentation_step(g, batch, class_weight=w)
    torch.manual_seed(5)
    noisy = torch.tensor([[0.0, 0, 1]] * 2) + UP_JITTER * torch.randn(2, 3)
    torch.testing.assert_close(loss, segmentation_loss(g(x, mask, up=noisy), y, class_weight=w))
    assert calls == [] and "up_err_deg" not in stats
    hook.remove()


@pytest.mark.parametrize("name", list(MODELS))
def test_make_model_scales_the_channels_and_the_checkpoint_keeps_them(tmp_path, name):
    from usf_graph.train.engine import save_checkpoint

    full, half = make_model(name, level=3), make_model(name, level=3, channel_scale=0.5)
    for key in ("channels", "aspp_channels", "low_channels"):
        if key in full.config:  # every default is even, so halving is exact
            want = full.config[key]
            want = [c // 2 for c in want] if isinstance(want, list) else want // 2
            assert half.config[key] == want, key
    size = sum(p.numel() for p in half.parameters()) / sum(p.numel() for p in full.parameters())
    gravity = getattr(full, "gravity", None)
    if gravity is not None:  # the up estimate keeps its own channels
        assert [p.shape for p in half.gravity.parameters()] == [p.shape for p in gravity.parameters()]
        dense = sum(p.numel() for p in gravity.parameters())
        size = (sum(p.numel() for p in half.parameters()) - dense) / (
            sum(p.numel() for p in full.parameters()) - dense)
    assert 0.2 < size < 0.35, size  # dense layers are a quarter, the inputs' layers more
    save_checkpoint(tmp_path / "m.pt", half, {"model": name, "size": 32, **half.config}, {})
    back = load_protocol_model(tmp_path / "m.pt").model
    assert {k: v.shape for k, v in back.state_dict().items()} == {
        k: v.shape for k, v in half.state_dict().items()}
    with pytest.raises(ValueError, match="channel scale"):
        make_model(name, level=3, channel_scale=0.0)


def test_an_unknown_model_stops_the_protocol_before_it_renders(tmp_path):
    with pytest.raises(ValueError, match=r"unknown models \['planar_deeplab'\]"):
        run(root=tmp_path / "rooms", out=tmp_path / "out", progress=False,
            models=("spherical_unet", "planar_deeplab"))
    assert not (tmp_path / "rooms").exists()


def test_a_plan_the_models_cannot_train_is_refused_before_any_rendering(tmp_path, capsys):
    for kw, said in ((dict(models=()), "no models to train"),
                     (dict(models=("spherical_unet", "unet")), r"unknown models \['unet'\]"),
                     (dict(level=2), "level 2: the spherical models need icosahedral:3 or finer"),
                     (dict(fov_share=1.5), r"random fields of view must be in \[0, 1\], got 1.5"),
                     (dict(balance=-1.0), "balance is the class weights' power")):
        with pytest.raises(ValueError, match=said):
            run(root=tmp_path / "rooms", out=tmp_path / "out", progress=False, **kw)
    with pytest.raises(ValueError, match="give a level of at least 3"):
        make_model("spherical_deeplab", level=2)
    assert main(["train", "seg", "--root", str(tmp_path / "rooms"), "--level", "1"]) == 2
    assert "level 1: the spherical models need icosahedral:3" in capsys.readouterr().err
    assert not (tmp_path / "rooms").exists() and not (tmp_path / "out").exists()


def test_make_model_builds_the_protocols_models():
    """The protocol's recipe: icosahedral:5, an up estimate, oriented fields instead of
    gradient pairs, oriented kernels on every coarser level of the DeepLab only."""
    deeplab, unet = make_model("spherical_deeplab"), make_model("spherical_unet", level=4)
    for net, level, convs in ((deeplab, 5, 4), (unet, 4, None)):
        c = net.config
        assert (c["level"], c["gravity"], c["upright"], c["gray"]) == (level, True, True, False)
        assert (c["pairs"], c["up_fields"], c["upright_convs"]) == (0, 4, convs)
    plain = make_model("spherical_deeplab", level=3, upright=False).config
    assert not plain["upright"] and plain["upright_convs"] is None and plain["pairs"] > 0
    assert make_model("planar_unet", gray=True).gray and make_model("spherical_unet", level=3, gray=True).config["gray"]


def test_balanced_weights_are_median_frequency_weights_to_a_power():
    # class counts 3, 2, 4, 1; the ignored label and one past the classes are not counted
    y = torch.tensor([[0, 0, 0, 1, 1, IGNORE], [2, 2, 2, 2, 3, 4]])
    full = torch.tensor([2.5 / 3, 2.5 / 2, 2.5 / 4, 2.5 / 1])  # median 2.5 over each count
    train = SimpleNamespace(y=y)
    torch.testing.assert_close(balanced_weights(train, 1.0, num_classes=4), full)
    torch.testing.assert_close(balanced_weights(train, num_classes=4), full ** 0.5)  # the default
    assert balanced_weights(train, 0.0, num_classes=4) is None
    # with six classes label 4 counts (once) and class 5 is never seen: it weighs 0, and
    # the median is over the classes seen (counts 3, 2, 4, 1, 1: median 2)
    torch.testing.assert_close(balanced_weights(train, 1.0, num_classes=6),
                               torch.tensor([2 / 3, 1.0, 0.5, 2.0, 2.0, 0.0]))
