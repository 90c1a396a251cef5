"""Which protocol model a checkpoint holds, rebuilt from it: the one reader that the
``usf-graph eval seg|det`` commands and the examples starting from a protocol checkpoint
share, so that they agree on how a checkpoint says what it is."""

from __future__ import annotations

from dataclasses import dataclass

from torch import nn

from ..models import PlanarDetector, SphericalDetector
from ..scenes import PANDORA_CLASSES
from . import det, seg
from .engine import defaults, load_checkpoint
from .mnist import classifier_kind


@dataclass
class ProtocolCheckpoint:
    """A protocol model rebuilt from its checkpoint.

    ``path``: where it was read; ``task``: ``"seg"`` or ``"det"``; ``name``: a
    :data:`usf_graph.train.seg.MODELS` key, or ``"spherical_detector"`` /
    ``"planar_detector"``; ``config``: the saved config, as saved
    (hand it back to :func:`~usf_graph.train.save_checkpoint` to save a model of the same
    kind); ``size``: the panorama height it was trained at (the saved one, else the
    task's protocol default); ``metrics``: the metrics saved with it; ``dataset``: what it
    was trained on, ``rooms``, ``stanford2d3ds`` (with its ``fold``), ``woodscape`` (with its
    images' ``scale``) or ``pandora``; ``seed``:
    a rooms run's seed (None where the checkpoint predates recording it); ``materials``: its
    rooms' (:mod:`usf_graph.scenes.materials`; ``"random"`` where not recorded);
    ``provenance``: the code and command that made it
    (:func:`~usf_graph.train.provenance.provenance`; None before session 51)."""

    path: str
    task: str
    name: str
    model: nn.Module
    config: dict
    size: int
    metrics: dict
    dataset: str = "rooms"
    fold: int | None = None
    seed: int | None = None
    materials: str = "random"
    provenance: dict | None = None
    scale: float | None = None

    @property
    def planar(self) -> bool:
        return self.name in ("planar_unet", "planar_detector")

    def rooms_seed(self, seed: int | None = None) -> int:
        """The seed of the rooms to score this checkpoint on: ``seed``, else its own (0 where
        it predates the record, with a note). An error where those test rooms are the ones
        it trained on: the training rooms of seed s + 1 are the test rooms of seed s
        (:func:`~usf_graph.datasets.rooms.split_seed`)."""
        from ..datasets.rooms import split_seed

        chosen = seed if seed is not None else (self.seed if self.seed is not None else 0)
        if self.seed is None:
            print(f"note: {self.path} does not record its training seed (saved before session "
                  f"34); scoring it on the test rooms of seed {chosen}, which are the training "
                  f"rooms of seed {split_seed('test', chosen)}")
        elif split_seed("test", chosen) == split_seed("train", self.seed):
            raise ValueError(f"the test rooms of seed {chosen} are the rooms {self.path} trained "
                             f"on (seed {self.seed}); score it with seed {self.seed}")
        return chosen

    def require(self, task: str | None = None, spherical: bool = False) -> ProtocolCheckpoint:
        """Itself, or a clear error if it is not of ``task`` (``"seg"``, ``"det"``) or,
        with ``spherical``, if it is planar."""
        if (task or self.task) != self.task or (spherical and self.planar):
            wanted = ("a spherical " if spherical else "a ") + (task or "seg|det")
            raise ValueError(f"{self.path} holds the {self.task} model {self.name!r}, not "
                             f"{wanted} model; give a checkpoint of 'usf-graph train "
                             f"{task or 'seg|det'}'")
        return self


def _default_size(task: str) -> int:
    return defaults(seg.run if task == "seg" else det.run)["size"]


#: the names :func:`model_name` gives ``usf-graph train mnist``'s two models
CLASSIFIERS = {"spherical": "spherical_classifier", "planar": "planar_cnn"}


def model_name(blob: dict) -> str | None:
    """The name of the model a loaded checkpoint holds, the one rule every reader follows:
    ``usf-graph train mnist``'s (:data:`CLASSIFIERS`), a segmentation model's own
    (``config["model"]``), else a detector's (``planar_detector`` where the config has the
    image ``height``, ``spherical_detector``); None for a config none of these."""
    if (kind := classifier_kind(blob)) is not None:
        return CLASSIFIERS[kind]
    cfg = blob.get("config") or {}
    if cfg.get("model") is not None:
        return cfg["model"]
    if "num_classes" in cfg:
        return "planar_detector" if "height" in cfg else "spherical_detector"
    return None


def load_protocol_model(path, weights: bool = True) -> ProtocolCheckpoint:
    """The model a checkpoint of ``usf-graph train seg|det`` (or of an example saving one
    of the same kind) holds, with its trained weights (``weights=False``: freshly
    initialized, e.g. to load another state of it). A segmentation checkpoint names its
    model (``config["model"]``); a detection one does not, and a planar detector's config
    has the image ``height``."""
    blob = load_checkpoint(path)
    cfg = dict(blob["config"])
    name, size = model_name(blob), cfg.pop("size", None)
    cfg.pop("model", None)
    data = blob.get("data", {})  # what it was trained on: dataset, and fold or seed
    dataset, fold, seed = data.get("dataset"), data.get("fold"), data.get("seed")
    if name in CLASSIFIERS.values():
        raise ValueError(f"{path} holds the {classifier_kind(blob)} MNIST classifier of "
                         "'usf-graph train mnist', not a seg|det model; score it with "
                         "'usf-graph eval mnist'")
    if name in seg.MODELS:
        task, model = "seg", seg.MODELS[name].from_config(cfg)
    elif name in ("planar_detector", "spherical_detector"):
        task = "det"
        model = (PlanarDetector if name == "planar_detector" else SphericalDetector).from_config(cfg)
    else:
        raise ValueError(f"{path} is not a checkpoint of 'usf-graph train seg|det' (its config "
                         f"names model {name!r})")
    if weights:
        model.load_state_dict(blob["state_dict"])
    if dataset is None:  # saved before checkpoints named their data: PANDORA's by its classes
        dataset = "pandora" if task == "det" and model.num_classes == len(PANDORA_CLASSES) else "rooms"
    return ProtocolCheckpoint(str(path), task, name, model, blob["config"],
                              size or _default_size(task), blob.get("metrics", {}), dataset, fold,
                              seed, data.get("materials", "random"), blob.get("provenance"),
                              data.get("scale"))
