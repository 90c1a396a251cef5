"""The training engine: checkpoints and a two-process DDP step."""

import json
import os
import re
import shutil
import socket
import subprocess
import sys

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.helpers import CodeOnLoad
from usf_graph.models import SphericalClassifier
from usf_graph.train.engine import load_checkpoint, save_checkpoint


def test_checkpoint_round_trip(tmp_path):
    torch.manual_seed(0)
    m = SphericalClassifier(level=2, channels=(4, 8), basis="gaussian", num_basis=3)
    save_checkpoint(tmp_path / "m.pt", m, m.config, {"acc": 0.5})
    m2 = SphericalClassifier.from_config(load_checkpoint(tmp_path / "m.pt")["config"])
    blob = load_checkpoint(tmp_path / "m.pt", m2)
    assert blob["metrics"]["acc"] == 0.5
    x = torch.randn(3, 162, 1)
    m.eval(), m2.eval()
    assert torch.equal(m(x), m2(x))
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="not a readable usf-graph checkpoint: corrupt") as e:
        load_checkpoint(tmp_path / "bad.pt")
    # torch's own advice (load with weights_only=False) is not passed on as a fix
    assert "Re-running" not in str(e.value) and "do not load a file you do not trust" in str(e.value)
    (tmp_path / "cut.pt").write_bytes((tmp_path / "m.pt").read_bytes()[:100])
    with pytest.raises(ValueError, match=r"truncated.*\(PytorchStreamReader failed"):
        load_checkpoint(tmp_path / "cut.pt")
    with pytest.raises(FileNotFoundError):
        load_checkpoint(tmp_path / "missing.pt")
    # a checkpoint from before the gradient pairs (no "pairs" in its config) still loads
    old = {k: v for k, v in m.config.items() if k not in ("pairs", "pair_stages")}
    plain = SphericalClassifier(**old, pairs=0)
    assert not len(SphericalClassifier.from_config(old).pairs)
    SphericalClassifier.from_config(old).load_state_dict(plain.state_dict())


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_process_ddp_step_equals_one_process(tmp_path):
    """Each process takes its share of every batch, also of batches drawn by group: two
    processes under torchrun end where this one does."""
    from tests.train.ddp_worker import CASES, NoNorm, step

    torchrun = shutil.which("torchrun", path=os.path.dirname(sys.executable))
    worker = os.path.join(os.path.dirname(__file__), "ddp_worker.py")
    # loopback only: the sandbox's other interfaces may not route between processes
    env = {**os.environ, "OMP_NUM_THREADS": "1", "USF_GRAPH_CACHE": "off",
           "GLOO_SOCKET_IFNAME": "lo"}
    subprocess.run([torchrun, "--nproc_per_node=2", "--master_addr=127.0.0.1",
                    f"--master_port={_free_port()}", worker, str(tmp_path)],
                   check=True, env=env, timeout=300)
    torch.manual_seed(0)
    torch.randn(8, 162, 1)
    start = NoNorm().state_dict()  # the worker's initial parameters
    for case in CASES:
        seen = []
        one = step(case, seen)
        assert sum(seen) == 8
        for rank in (0, 1):  # in one group of two, each process a half of every batch
            got = json.loads((tmp_path / f"{case}_{rank}.json").read_text())
            assert got["world"] == 2 and sum(got["seen"]) == 4 and len(got["seen"]) == len(seen), got
        two = torch.load(tmp_path / f"{case}.pt", weights_only=True)
        assert one.keys() == two.keys()
        moved = 0.0
        for k in one:
            assert torch.allclose(one[k], two[k], atol=1e-9, rtol=0), (case, k, (one[k] - two[k]).abs().max())
            if k in start and one[k].is_floating_point():
                moved = max(moved, float((one[k] - start[k].double()).abs().max()))
        assert moved > 1e-4, case  # the step did change the parameters


def test_a_diverging_run_stops_with_a_clear_error_and_keeps_the_last_epoch(tmp_path):
    """A step whose loss turns NaN (a learning rate too high makes the weights inf) stops
    training with an error that says what to do, and last.pt keeps the finished epoch."""
    from torch.utils.data import TensorDataset

    from usf_graph.train.engine import fit

    torch.manual_seed(0)
    model = torch.nn.Linear(2, 1)
    data = TensorDataset(torch.randn(8, 2), torch.randn(8, 1))
    calls = []

    def step(m, batch):
        x, y = batch
        calls.append(1)
        loss = ((m(x) - y) ** 2).mean()
        return (loss * float("nan") if len(calls) == 6 else loss), {}, len(x)

    with pytest.raises(FloatingPointError, match=r"loss is nan at epoch 2, batch 2: training "
                       r"diverged; lower the learning rate \(lr=0.01\)"):
        fit(model, data, epochs=3, batch_size=2, lr=0.01, log_dir=tmp_path, progress=False,
            step=step)
    blob = load_checkpoint(tmp_path / "last.pt")
    assert blob["epoch"] == 1 and all(torch.isfinite(v).all() for v in blob["state_dict"].values())
    calls.clear()  # without a log folder there is no last.pt to point to
    with pytest.raises(FloatingPointError, match=r"check the inputs for NaN$"):
        fit(model, data, epochs=3, batch_size=2, lr=0.01, progress=False, step=step)


def test_tensorboard_gets_every_epochs_row_and_is_closed(tmp_path, monkeypatch):
    """With ``tensorboard`` installed (a stand-in here: the suite does not install it), each
    epoch's metrics.csv row goes to TensorBoard as scalars at that epoch, and the writer is
    closed, also when training stops early, so that its last events reach the disk."""
    import types

    from torch.utils.data import TensorDataset

    from usf_graph.train.engine import fit

    writers = []

    class Writer:
        def __init__(self, log_dir):
            self.log_dir, self.scalars, self.closed = log_dir, [], False
            writers.append(self)

        def add_scalar(self, tag, value, step):
            self.scalars.append((tag, value, step))

        def close(self):
            self.closed = True

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.close()

    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard",
                        types.SimpleNamespace(SummaryWriter=Writer))
    torch.manual_seed(0)
    data = TensorDataset(torch.randn(8, 2), torch.randn(8, 1))

    def step(m, batch):
        x, y = batch
        return ((m(x) - y) ** 2).mean(), {}, len(x)

    hist = fit(torch.nn.Linear(2, 1), data, epochs=2, batch_size=4, lr=0.01, log_dir=tmp_path,
               progress=False, step=step)["history"]
    (w,) = writers
    assert w.log_dir == str(tmp_path) and w.closed
    assert w.scalars == [(k, v, row["epoch"]) for row in hist for k, v in row.items() if k != "epoch"]

    def stop(epoch, row):
        raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        fit(torch.nn.Linear(2, 1), data, epochs=2, batch_size=4, lr=0.01, log_dir=tmp_path / "b",
            progress=False, step=step, on_epoch=stop)
    assert writers[1].closed and len(writers[1].scalars) == 2  # train_loss and lr of epoch 1


@pytest.mark.parametrize("kw, said", [
    (dict(epochs=0), "epochs and batch_size must be whole numbers of at least 1, got 0 and 2"),
    (dict(epochs=-1), "got -1 and 2"), (dict(batch_size=0), "got 1 and 0"),
    (dict(lr=0.0), "the learning rate must be a finite number above 0, got 0.0"),
    (dict(lr=float("nan")), "the learning rate"), (dict(train=[]), "the training set is empty")])
def test_fit_refuses_a_plan_that_trains_nothing(kw, said):
    from torch.utils.data import TensorDataset

    from usf_graph.train.engine import fit

    model = torch.nn.Linear(2, 1)
    args = dict(train=TensorDataset(torch.randn(4, 2), torch.randn(4, 1)), epochs=1,
                batch_size=2, lr=0.01, progress=False, name="tiny")
    with pytest.raises(ValueError, match=re.escape(said)) as e:
        fit(model, **{**args, **kw})
    assert str(e.value).startswith("tiny: ")


@pytest.mark.parametrize("frozen", [False, True])
def test_frozen_norms_keep_their_statistics_while_their_scale_trains(frozen):
    from torch.utils.data import TensorDataset

    from usf_graph.nn import MaskedBatchNorm
    from usf_graph.train.engine import fit

    class Net(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.lin, self.bn, self.mbn = torch.nn.Linear(2, 3), torch.nn.BatchNorm1d(3), MaskedBatchNorm(3)

        def forward(self, x):
            return self.mbn(self.bn(self.lin(x)))

    torch.manual_seed(0)
    net = Net()
    data = TensorDataset(5 + 3 * torch.randn(16, 2), torch.randn(16, 3))
    before = {k: v.clone() for k, v in net.state_dict().items()}

    def step(m, batch):
        x, y = batch
        # in training mode a norm uses its batch's statistics; frozen, its running ones
        for bn in (m.bn, m.mbn):
            assert bn.training != frozen
        return ((m(x) - y) ** 2).mean(), {}, len(x)

    fit(net, data, epochs=2, batch_size=4, lr=0.05, progress=False, step=step, frozen_norms=frozen)
    after = net.state_dict()
    for name in ("bn", "mbn"):
        stats_same = all(torch.equal(before[f"{name}.{s}"], after[f"{name}.{s}"])
                         for s in ("running_mean", "running_var"))
        assert stats_same == frozen
        assert not torch.equal(before[f"{name}.weight"], after[f"{name}.weight"])  # it trains


def test_scaled_channels_is_a_width_multiplier_of_the_defaults():
    from usf_graph.models import PlanarUNet, SphericalDeepLabV3
    from usf_graph.train import scaled_channels

    # SphericalDeepLabV3: channels (32, 64, 128), aspp 128, low-level 32
    assert scaled_channels(SphericalDeepLabV3, 0.5) == {
        "channels": [16, 32, 64], "aspp_channels": 64, "low_channels": 16}
    # rounded, and never below 8 channels
    assert scaled_channels(PlanarUNet, 0.3) == {"channels": [10, 19, 38, 38]}
    assert scaled_channels(PlanarUNet, 0.1) == {"channels": [8, 8, 13, 13]}
    assert scaled_channels(PlanarUNet, 1.0) == {}
    assert scaled_channels(SphericalClassifier, 2.0) == {"channels": [64, 128, 256, 256]}
    for bad in (0.0, -1.0, float("nan"), float("inf"), 5.0):
        with pytest.raises(ValueError, match="channel scale must be in"):
            scaled_channels(PlanarUNet, bad)


def test_resume_goes_on_as_an_uninterrupted_run_would(tmp_path):
    """A run stopped after its first epoch and resumed ends with the weights of one that
    ran through, bitwise: with random fields of view cut by the collate_fn (its draws are
    saved) and steps that draw from torch's generator (the known up's jitter). A finished
    run resumes by loading; another plan or config is refused."""
    from functools import partial

    from usf_graph.train.engine import fit
    from usf_graph.train.seg import (
        ThroughRandomFields,
        make_model,
        protocol_sets,
        segmentation_step,
    )

    train = protocol_sets(tmp_path / "rooms", size=16, level=3, num_train=4, num_test=1,
                          tests=(), progress=False)["train"]
    step = partial(segmentation_step, class_weight=None)

    def run(log_dir, resume=False, stop_after=None, lr=3e-3):
        torch.manual_seed(1)
        net = make_model("spherical_unet", level=3)

        def stop(epoch, row):  # an interruption (Ctrl-C) after that epoch
            if epoch + 1 == stop_after:
                raise KeyboardInterrupt
        cut = ThroughRandomFields(train.grid.pos, share=0.5, seed=3)
        fit(net, train, epochs=3, batch_size=2, lr=lr, seed=0, log_dir=log_dir, config=net.config,
            resume=resume, progress=False, step=step, collate_fn=cut, on_epoch=stop)
        return net.state_dict()

    through = run(tmp_path / "through")
    with pytest.raises(KeyboardInterrupt):
        run(tmp_path / "cut", stop_after=1)
    assert load_checkpoint(tmp_path / "cut" / "last.pt")["epoch"] == 1
    resumed = run(tmp_path / "cut", resume=True)
    assert all(torch.equal(through[k], resumed[k]) for k in through)
    assert all(torch.equal(through[k], v) for k, v in run(tmp_path / "cut", resume=True).items())
    with pytest.raises(ValueError, match="was written with plan .* resume with the same options"):
        run(tmp_path / "cut", resume=True, lr=1e-3)


def test_evaluate_weights_every_sample_once():
    """Batches of 4, 4 and 2: the means are over the ten samples, not over the batches."""
    from torch.utils.data import TensorDataset

    from usf_graph.train.engine import evaluate

    torch.manual_seed(0)
    model, x = torch.nn.Linear(3, 4), torch.randn(10, 3)
    with torch.no_grad():
        best = model(x).argmax(1)
    y = torch.where(torch.arange(10) < 3, best, (best + 1) % 4)  # three right
    got = evaluate(model, TensorDataset(x, y), batch_size=4, progress=False)
    assert set(got) == {"loss", "acc"} and got["acc"] == pytest.approx(0.3, abs=1e-12)
    with torch.no_grad():
        assert got["loss"] == pytest.approx(torch.nn.functional.cross_entropy(model(x), y).item(), rel=1e-6)


def test_fit_draws_every_sample_once_an_epoch_in_a_new_order():
    from torch.utils.data import TensorDataset

    from usf_graph.train.engine import fit

    model, order = torch.nn.Linear(1, 2), []

    def step(m, batch):
        x, y = batch
        order.extend(int(v) for v in x[:, 0])
        return torch.nn.functional.cross_entropy(m(x), y), {}, len(y)

    data = TensorDataset(torch.arange(12.0)[:, None], torch.zeros(12, dtype=torch.long))
    fit(model, data, epochs=2, batch_size=4, progress=False, step=step)
    first, second = order[:12], order[12:]
    assert sorted(first) == sorted(second) == list(range(12))
    assert first != list(range(12)) and second != first  # shuffled, anew each epoch


def test_fit_batches_a_list_of_graphs_as_pyg_does():
    from torch_geometric.data import Batch, Data

    from usf_graph.train.engine import fit

    model, seen = torch.nn.Linear(1, 2), []

    def step(m, batch):
        assert isinstance(batch, Batch)
        seen.append(batch.num_graphs)
        return m(batch.x).sum(), {}, batch.num_graphs

    graphs = [Data(x=torch.rand(n, 1)) for n in (2, 3, 4)]  # of different sizes
    fit(model, graphs, epochs=1, batch_size=2, progress=False, step=step)
    assert sorted(seen) == [1, 2]


def test_fit_reports_each_epoch_with_its_validation():
    from torch.utils.data import TensorDataset

    from usf_graph.train.engine import evaluate, fit

    torch.manual_seed(0)
    model = torch.nn.Linear(3, 4)
    train = TensorDataset(torch.randn(12, 3), torch.randint(0, 4, (12,)))
    val = TensorDataset(torch.randn(10, 3), torch.randint(0, 4, (10,)))
    history = fit(model, train, val, epochs=2, batch_size=4, lr=0.01, progress=False)["history"]
    assert [row["epoch"] for row in history] == [1, 2]
    assert set(history[0]) == {"epoch", "train_loss", "train_acc", "lr", "val_loss", "val_acc"}
    assert abs(history[-1]["lr"]) < 1e-12 < history[0]["lr"]  # the cosine's end
    final = evaluate(model, val, progress=False)
    assert history[-1]["val_loss"] == pytest.approx(final["loss"], rel=1e-6)
    assert history[-1]["val_acc"] == final["acc"]


def test_seed_everything_seeds_every_generator_and_asks_for_deterministic_kernels():
    import random

    from usf_graph.train.engine import seed_everything

    def draws():
        return random.random(), float(np.random.rand()), float(torch.rand(1))

    torch.use_deterministic_algorithms(False)
    seed_everything(3)
    first = draws()
    assert torch.are_deterministic_algorithms_enabled()
    assert torch.is_deterministic_algorithms_warn_only_enabled()  # warns where it cannot
    seed_everything(3, deterministic=False)
    assert draws() == first


def test_a_checkpoint_that_would_run_code_is_refused_unrun(tmp_path):
    mark = tmp_path / "ran"
    torch.save({"state_dict": {}, "config": {}, "x": CodeOnLoad(mark)}, tmp_path / "evil.pt")
    with pytest.raises(ValueError, match="is not a readable usf-graph checkpoint.*do not load a file"):
        load_checkpoint(tmp_path / "evil.pt")
    assert not mark.exists()


def test_resolve_device_gives_what_the_machine_has_and_names_what_it_lacks(monkeypatch):
    from usf_graph.train.devices import resolve_device

    cpu = torch.device("cpu")
    assert resolve_device(None) == cpu and resolve_device("cpu") == cpu
    for bad, why in (("tpu", "unknown device 'tpu'"), ("meta", "trains on cpu or cuda"),
                     ("mps", "trains on cpu or cuda")):
        with pytest.raises(ValueError, match=why):
            resolve_device(bad)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == cpu
    with pytest.raises(ValueError, match="sees no CUDA GPU.*use --device cpu"):
        resolve_device("cuda")
    # a machine with two GPUs, in the second process of a torchrun
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    monkeypatch.delenv("LOCAL_RANK", raising=False)  # no torchrun: the first GPU
    assert resolve_device("cuda") == torch.device("cuda", 0) == resolve_device("auto")
    monkeypatch.setenv("LOCAL_RANK", "1")
    assert resolve_device("cuda") == torch.device("cuda", 1) == resolve_device("auto")
    assert resolve_device("cuda:0") == torch.device("cuda", 0)
    with pytest.raises(ValueError, match="has 2 GPU"):
        resolve_device("cuda:2")


@pytest.mark.parametrize("world", [None, "1"])
def test_one_process_joins_no_group(monkeypatch, world):
    """No torchrun, or torchrun with one process: no process group to join (gloo would
    want a rendezvous address for nothing)."""
    from usf_graph.train.devices import is_distributed, setup_distributed

    monkeypatch.delenv("MASTER_ADDR", raising=False)
    if world is None:
        monkeypatch.delenv("WORLD_SIZE", raising=False)
    else:
        monkeypatch.setenv("WORLD_SIZE", world)
    assert setup_distributed() == (0, 1) and not is_distributed()


def test_to_device_moves_every_tensor_of_a_batch_and_nothing_else():
    from torch_geometric.data import Batch, Data

    from usf_graph.train.devices import model_device, to_device

    pyg = Batch.from_data_list([Data(x=torch.rand(3, 2), pos=torch.rand(3, 3)) for _ in range(2)])
    batch = (torch.rand(2), None, [pyg, 3], {"mask": torch.ones(4, dtype=torch.bool), "name": "a"})
    meta = torch.device("meta")  # a device every torch has, CPU-only ones too
    out = to_device(batch, meta)
    assert type(out) is tuple and type(out[2]) is list and out[1] is None
    assert out[2][1] == 3 and out[3]["name"] == "a"
    moved = [out[0], out[2][0].x, out[2][0].pos, out[2][0].batch, out[2][0].ptr, out[3]["mask"]]
    assert all(t.device == meta for t in moved)
    assert out[3]["mask"].dtype == torch.bool
    assert batch[0].device.type == "cpu"  # tensors are copied; a PyG batch moves itself, as .to() does
    assert out[2][0] is pyg and pyg.x.device == meta
    assert model_device(torch.nn.Linear(2, 3)).type == "cpu"
    assert model_device(torch.nn.Linear(2, 3, device=meta)) == meta
    assert model_device(torch.nn.Identity()).type == "cpu"


def test_is_planar_tells_the_image_models_from_the_spherical_ones():
    from types import SimpleNamespace

    from usf_graph.models import (
        PlanarDeepLab,
        PlanarDetector,
        PlanarUNet,
        SphericalDeepLabV3,
        SphericalDetector,
        SphericalUNet,
    )
    from usf_graph.train.devices import is_planar

    image = torch.rand(1, 3, 32, 64)
    for planar in (PlanarUNet(3, channels=(4, 8)), PlanarDeepLab(3, channels=(4, 8), aspp_channels=4),
                   PlanarDetector(3, height=32, width=64, channels=(4, 8))):
        assert is_planar(planar) and is_planar(SimpleNamespace(module=planar))  # DDP's wrapper
        planar(image)  # what is_planar promises: it takes [B, C, H, W]
    for spherical in (SphericalUNet(3, level=2, min_level=1, channels=(4, 4)),
                      SphericalDeepLabV3(3, level=2, channels=(4, 4), aspp_channels=4, rates=(2,),
                                         low_channels=4),
                      SphericalDetector(3, input_level=2, head_level=2, min_level=1, channels=(4, 4))):
        assert not is_planar(spherical) and not is_planar(SimpleNamespace(module=spherical))


DEVICES = ("cpu", "cuda")  # the GPU test's pair (a CPU run of the test itself: ("cpu", "cpu"))


def before_a_norm(net) -> set[str]:
    """Names of the conv biases that a BatchNorm follows. The norm takes their gradient to 0
    up to rounding, and Adam scales rounding to steps of the learning rate's size, so
    they wander differently on two devices without changing what the network computes.
    (The up estimate's head is left out of the weights' comparison too: its window follows
    the argmax of its scores, which rounding flips between near ties. Its errors are
    compared instead. Both seen on an H200, session 37.)"""
    return {f"{name}.convs.{k}.bias" if name else f"convs.{k}.bias"
            for name, m in net.named_modules() if hasattr(m, "convs") and hasattr(m, "norms")
            for k in range(len(m.convs))}


GPU = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU (CI has none)")


@GPU
def test_on_a_gpu_segmentation_training_and_prediction_follow_the_cpu(tmp_path):
    """The segmentation recipe through ``fit(device="cuda")``: the same draws (batches,
    fields of view, the up's jitter) as on the CPU, so each epoch's loss, the weights after
    two epochs and the predictions (the protocol's and ``usf-graph predict``'s) agree up to
    float32 rounding."""
    from functools import partial

    from usf_graph.train import seg, seg_eval
    from usf_graph.train.apply import segment_image
    from usf_graph.train.engine import fit
    from usf_graph.train.gravity import up_report, views_up

    sets = seg.protocol_sets(tmp_path / "rooms", size=16, level=3, num_train=4, num_test=2,
                             tests=("d",), progress=False)
    step = partial(seg.segmentation_step, class_weight=torch.ones(13))
    nets, preds, ups, own, losses = [], [], [], [], []
    for dev in DEVICES:
        torch.manual_seed(1)
        net = seg.make_model("spherical_unet", level=3)
        cut = seg.ThroughRandomFields(sets["train"].grid.pos, share=0.5, seed=3)
        losses.append(fit(net, sets["train"], epochs=2, batch_size=2, lr=1e-3, seed=0,
                          progress=False, step=step, collate_fn=cut, device=dev)["history"])
        assert all(p.device.type == dev for p in net.parameters())
        nets.append({k: v.detach().cpu() for k, v in net.named_parameters()
                     if k not in before_a_norm(net) and not k.startswith("gravity.head.")})
        preds.append(seg_eval.predict(net, sets["d"], progress=False)[1])
        ups.append(up_report(net.gravity, sets["d"].x, sets["d"].mask[0], views_up(sets["d"])))
        own.append(segment_image(net, sets["d"].image[0].numpy(), sets["d"].camera)["points"])
    for a, b in zip(*losses):
        assert abs(a["train_loss"] - b["train_loss"]) < 1e-4 * abs(a["train_loss"]), (a, b)
    off = {k: float((v - nets[1][k]).norm() / v.norm()) for k, v in nets[0].items()
           if not torch.allclose(v.double(), nets[1][k].double(), rtol=1e-3, atol=1e-4)}
    assert not off, off
    assert (preds[0] == preds[1]).mean() > 0.99
    assert (own[0] == own[1]).mean() > 0.99  # usf-graph predict's path
    # the head's weights differ by a few learning-rate steps (before_a_norm): on the H200
    # the two untrained estimates' median errors were 96.66 and 95.16 degrees
    assert ups[0]["gross"] == ups[1]["gross"], (ups[0], ups[1])
    assert abs(ups[0]["median_err_deg"] - ups[1]["median_err_deg"]) < 3.0, (ups[0], ups[1])


@GPU
def test_on_a_gpu_detection_training_and_prediction_follow_the_cpu(tmp_path):
    """The detection recipe through ``fit(device="cuda")`` scores the test views as the CPU's
    run does."""
    from usf_graph.models import SphericalDetector
    from usf_graph.train import det
    from usf_graph.train.engine import fit

    rooms = det.protocol_sets(tmp_path / "rooms", size=16, grid="icosahedral:3", num_train=4,
                              num_test=2, progress=False)
    data = det.DetectionSet.spherical(rooms["train"])
    found = []
    for dev in DEVICES:
        torch.manual_seed(1)
        net = SphericalDetector(num_classes=12, input_level=3, head_level=2, min_level=1,
                                channels=(4, 6, 8), pairs=2, gradient_fields=2, gravity=True,
                                upright=True)
        fit(net, data, epochs=2, batch_size=2, lr=1e-3, seed=0, progress=False,
            step=det.detection_step, collate_fn=data.collate, device=dev)
        found.append(det.predict(net, det.DetectionSet.spherical(rooms["d"]), progress=False,
                                 threshold=0.0, k=5))
    assert len(found[0]) == len(found[1]) == 2
    for a, b in zip(*found):
        assert abs(a["scores"][0] - b["scores"][0]) < 1e-3


@settings(max_examples=40, deadline=None)
@given(groups=st.lists(st.integers(0, 3), min_size=1, max_size=30),
       batch_size=st.integers(1, 5), seed=st.integers(0, 5), epoch=st.integers(0, 3))
def test_group_batches_take_every_sample_once_and_never_mix_groups(groups, batch_size, seed, epoch):
    from usf_graph.train import group_batches

    batches = group_batches(groups, batch_size, seed, epoch)
    assert sorted(i for b in batches for i in b) == list(range(len(groups)))
    assert all(1 <= len(b) <= batch_size and len({groups[i] for i in b}) == 1 for b in batches)
    # as few batches as the groups allow, and the same draw for the same seed and epoch
    sizes = np.bincount(groups)
    assert len(batches) == sum(-(-n // batch_size) for n in sizes)
    assert group_batches(groups, batch_size, seed, epoch) == batches
    plain = group_batches(groups, batch_size, shuffle=False)
    assert [i for b in plain for i in b] == sorted(range(len(groups)), key=lambda i: (
        list(dict.fromkeys(groups)).index(groups[i]), i))


@pytest.mark.parametrize("bad", [0, -1, 2.5, 2.0])
def test_group_batches_want_a_whole_batch_size(bad):
    from usf_graph.train import group_batches

    with pytest.raises(ValueError, match=f"batch_size must be a whole number of at least 1, got {bad}"):
        group_batches([0, 0, 1], bad)


def test_field_groups_name_equal_masks_alike_and_batches_share_one_field(monkeypatch):
    from usf_graph.train import engine, field_groups

    a, b = torch.tensor([1, 1, 0, 0], dtype=torch.bool), torch.tensor([0, 1, 1, 0], dtype=torch.bool)
    g = field_groups(torch.stack([a, b, a, a, b]))
    assert g[0] == g[2] == g[3] != g[1] == g[4]
    with pytest.raises(ValueError, match=r"mask must be \[S, N\]"):
        field_groups(a)
    # under torchrun each process takes its share of every batch; one of a single sample
    # is repeated so that no process gets none (DDP would wait for it forever)
    monkeypatch.setattr(engine, "is_distributed", lambda: True)
    monkeypatch.setattr(engine.dist, "get_world_size", lambda: 2)
    shares = []
    for rank in (0, 1):
        monkeypatch.setattr(engine.dist, "get_rank", lambda r=rank: r)
        loader = engine._batches(list(range(5)), 2, True, 0, 0, collate_fn=list, groups=[0, 1, 0, 0, 1][:5])
        shares.append(list(loader))
    whole = engine.group_batches([0, 1, 0, 0, 1], 2, 0, 0)
    for k, batch in enumerate(whole):
        got = shares[0][k] + shares[1][k]
        assert len(shares[0][k]) == len(shares[1][k]) == 1  # a sample each, none twice over
        assert sorted(set(got)) == sorted(batch)
    # without groups, torch's DistributedSampler: each process a disjoint part of the
    # samples, in batches of its share of the global batch
    parts = []
    for rank in (0, 1):
        monkeypatch.setattr(engine.dist, "get_rank", lambda r=rank: r)
        parts.append(list(engine._batches(list(range(10)), 4, True, 0, 0, collate_fn=list)))
    assert [len(b) for b in parts[0]] == [len(b) for b in parts[1]] == [2, 2, 1]
    assert sorted(i for p in parts for b in p for i in b) == list(range(10))


def test_fit_under_torchrun_refuses_a_batch_the_processes_cannot_share(monkeypatch):
    """batch_size 4 over 3 processes would be global batches of 3 and 4 steps an epoch
    for 10 samples where the schedule counts 3 (the last at learning rate 0)."""
    from torch.utils.data import TensorDataset

    from usf_graph.train import engine

    monkeypatch.setattr(engine, "setup_distributed", lambda: (0, 3))
    data = TensorDataset(torch.randn(10, 2), torch.zeros(10, dtype=torch.long))
    with pytest.raises(ValueError, match="batch_size 4 does not split evenly over 3 processes; "
                                         "give a multiple of 3"):
        engine.fit(torch.nn.Linear(2, 2), data, batch_size=4, progress=False)


def test_fit_in_groups_batches_one_field_and_schedules_every_step(tmp_path):
    """Every batch of a grouped fit comes from one group; the cosine schedule counts the
    groups' batches (halfway through, the learning rate is half the initial one)."""
    from usf_graph.train.engine import fit

    groups = [0, 1, 2, 3, 4, 5, 0, 1]  # 6 batches of at most 2 an epoch, not 8 / 2
    seen = []

    class Tiny(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.zeros(()))

    def step(model, batch):
        seen.append(batch)
        return model.w ** 2 + model.w * 0, {}, len(batch)

    fit(Tiny(), list(range(8)), epochs=2, batch_size=2, lr=0.1, log_dir=tmp_path, progress=False,
        step=step, collate_fn=list, groups=groups)
    assert len(seen) == 12 and all(len({groups[i] for i in b}) == 1 for b in seen)
    rows = load_checkpoint(tmp_path / "last.pt")["metrics"]["history"]
    assert rows[0]["lr"] == pytest.approx(0.05, abs=1e-12) and rows[1]["lr"] == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ValueError, match="groups has 3 entries for 9 samples"):
        fit(Tiny(), list(range(9)), epochs=1, progress=False, step=step, collate_fn=list, groups=[0, 1, 2])
