import pytest
import torch

from usf_graph.models import (
    PlanarCNN,
    PlanarDetector,
    PlanarUNet,
    PointCloudNet,
    SignCheck,
    SphericalClassifier,
    SphericalDeepLabV3,
    SphericalDetector,
    SphericalUNet,
    UpNet,
)
from usf_graph.train.checkpoints import load_protocol_model, model_name
from usf_graph.train.engine import save_checkpoint


def _models():
    torch.manual_seed(0)
    unet = SphericalUNet(13, level=3, channels=(4, 4, 4, 4))
    planar = PlanarUNet(13, channels=(4, 4))
    detector = SphericalDetector(12, input_level=3, head_level=2, min_level=1, channels=(4, 4, 4))
    planar_detector = PlanarDetector(12, height=16, width=32, channels=(4, 4))
    return [  # (model, the config the protocol saves, task, name, size)
        (unet, {"model": "spherical_unet", "size": 32, **unet.config}, "seg", "spherical_unet", 32),
        (planar, {"model": "planar_unet", **planar.config}, "seg", "planar_unet", 96),
        (detector, detector.config, "det", "spherical_detector", 128),
        (planar_detector, planar_detector.config, "det", "planar_detector", 128),
    ]


@pytest.mark.parametrize("i", range(4))
def test_every_protocol_checkpoint_comes_back_as_its_model(tmp_path, i):
    model, cfg, task, name, size = _models()[i]
    with torch.no_grad():  # weights unlike a fresh initialization's
        for p in model.parameters():
            p.add_(torch.rand_like(p))
    save_checkpoint(tmp_path / "m.pt", model, cfg, {"score": 0.25})
    got = load_protocol_model(tmp_path / "m.pt")
    assert (got.task, got.name, got.size, got.planar) == (task, name, size, "planar" in name)
    assert type(got.model) is type(model) and got.config == cfg and got.metrics == {"score": 0.25}
    want = model.state_dict()
    assert all(torch.equal(v, want[k]) for k, v in got.model.state_dict().items())
    fresh = load_protocol_model(tmp_path / "m.pt", weights=False).model.state_dict()
    assert not all(torch.equal(v, want[k]) for k, v in fresh.items())
    assert got.require(task) is got
    other = "det" if task == "seg" else "seg"
    with pytest.raises(ValueError, match=f"holds the {task} model '{name}', not a {other} model; "
                       f"give a checkpoint of 'usf-graph train {other}'"):
        got.require(other)
    assert got.dataset == "rooms" and got.fold is None  # saved without its data: the rooms
    if got.planar:
        with pytest.raises(ValueError, match=f"not a spherical {task} model"):
            got.require(task, spherical=True)
    else:
        assert got.require(spherical=True) is got


def test_a_checkpoint_of_another_kind_is_refused(tmp_path):
    model = torch.nn.Linear(2, 2)
    save_checkpoint(tmp_path / "m.pt", model, {"model": "sign_check"}, {})
    with pytest.raises(ValueError, match="not a checkpoint of 'usf-graph train seg|det'.*'sign_check'"):
        load_protocol_model(tmp_path / "m.pt")
    save_checkpoint(tmp_path / "m.pt", model, {"in_channels": 2}, {})
    with pytest.raises(ValueError, match="not a checkpoint of 'usf-graph train seg|det'.*None"):
        load_protocol_model(tmp_path / "m.pt")


def test_one_rule_names_every_kind_of_checkpoint():
    """The names ``usf-graph info`` shows and that :func:`load_protocol_model` reads: from
    the configs the models save, MNIST's by what the run records or, before it did, by
    their configs' keys."""
    mnist = SphericalClassifier(level=2, channels=(4, 4))
    blobs = [({"config": cfg}, name) for _, cfg, _, name, _ in _models()]
    blobs += [({"config": mnist.config}, "spherical_classifier"),
              ({"config": PlanarCNN().config}, "planar_cnn"),
              ({"config": {}, "data": {"dataset": "mnist", "model": "planar"}}, "planar_cnn"),
              ({"config": {"in_channels": 2}}, None)]
    for blob, name in blobs:
        assert model_name(blob) == name, blob["config"]


def test_rooms_seed_defaults_to_the_checkpoints_and_refuses_its_training_rooms(capsys):
    """The test rooms of seed s are the training rooms of seed s + 1 (split_seed)."""
    from usf_graph.datasets.rooms import split_seed
    from usf_graph.train.checkpoints import ProtocolCheckpoint

    def ckpt(seed):
        return ProtocolCheckpoint("m.pt", "seg", "spherical_unet", None, {}, 96, {}, "rooms", None, seed)

    assert split_seed("test", 0) == split_seed("train", 1) == 1
    assert ckpt(1).rooms_seed() == 1 and ckpt(1).rooms_seed(2) == 2 and ckpt(1).rooms_seed(1) == 1
    with pytest.raises(ValueError, match="test rooms of seed 0 are the rooms m.pt trained on"):
        ckpt(1).rooms_seed(0)
    assert ckpt(None).rooms_seed() == 0 and ckpt(None).rooms_seed(3) == 3
    assert "training rooms of seed 4" in capsys.readouterr().out


def test_what_a_checkpoint_was_trained_on_and_an_mnist_one_refused(tmp_path):
    """The data a checkpoint records comes back; one saved before checkpoints recorded it
    is PANDORA's where its detector has PANDORA's 47 classes, else the rooms'. An MNIST
    classifier is sent to its own command."""
    from usf_graph.scenes import PANDORA_CLASSES

    det = SphericalDetector(len(PANDORA_CLASSES), input_level=3, head_level=2, min_level=1, channels=(4, 4, 4))
    save_checkpoint(tmp_path / "p.pt", det, det.config, {})
    assert load_protocol_model(tmp_path / "p.pt").dataset == "pandora"
    unet = SphericalUNet(13, level=3, channels=(4, 4, 4, 4))
    save_checkpoint(tmp_path / "s.pt", unet, {"model": "spherical_unet", **unet.config}, {},
                    extra={"data": {"dataset": "stanford2d3ds", "fold": 2}})
    got = load_protocol_model(tmp_path / "s.pt")
    assert (got.dataset, got.fold, got.seed) == ("stanford2d3ds", 2, None)
    mnist = SphericalClassifier(level=2, channels=(4, 4))
    save_checkpoint(tmp_path / "m.pt", mnist, mnist.config, {})
    with pytest.raises(ValueError, match="holds the spherical MNIST classifier.*'usf-graph eval mnist'"):
        load_protocol_model(tmp_path / "m.pt")


_NORM_STATS = ("running_mean", "running_var", "num_batches_tracked")


@pytest.mark.parametrize("make", [
    lambda: SphericalUNet(5, level=3, channels=(4, 6, 8), pairs=2, gravity=True, upright=True,
                          upright_convs=2, head_depth=1),
    lambda: SphericalDeepLabV3(5, level=3, channels=(4, 6), aspp_channels=8, rates=(2,),
                               low_channels=4, gravity=True, upright=True, upright_convs=2),
    lambda: SphericalDetector(12, input_level=3, head_level=2, min_level=1, channels=(4, 4, 4),
                              gravity=True, upright=True, upright_convs=2),
    lambda: SphericalClassifier(level=2, channels=(4, 8)),
    lambda: UpNet(3, level=3, channels=(4, 4)),
    lambda: SignCheck(level=3, channels=(4, 4)),
    lambda: PointCloudNet(4, channels=(4, 8), radii=(0.3, 0.6)),
], ids=["unet", "deeplab", "detector", "classifier", "upnet", "sign", "pointcloud"])
def test_a_checkpoint_holds_what_training_changes_and_no_geometry(make):
    """Every entry of a model's state is a parameter or a normalization's statistic: the
    geometry (graphs, kernels' tables, candidate directions) is rebuilt from the config,
    so checkpoints stay small and load into any grid refinement."""
    model = make()
    params = dict(model.named_parameters())
    extra = [k for k in model.state_dict() if k not in params and k.rsplit(".", 1)[-1] not in _NORM_STATS]
    assert not extra, extra[:5]
