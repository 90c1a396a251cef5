"""Training and evaluation loops shared by all tasks."""

from .devices import (
           model_device,
           resolve_device,
           setup_distributed,
           teardown_distributed,
           to_device,
)
from .engine import (
           defaults,
           evaluate,
           fit,
           freeze_norms,
           load_checkpoint,
           save_checkpoint,
           scaled_channels,
           seed_everything,
)

__all__ = ["defaults", "fit", "freeze_norms", "evaluate", "save_checkpoint", "load_checkpoint",
           "scaled_channels", "seed_everything", "setup_distributed", "teardown_distributed",
           "resolve_device", "model_device", "to_device"]
