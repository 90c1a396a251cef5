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
           field_groups,
           fit,
           freeze_norms,
           group_batches,
           load_checkpoint,
           save_checkpoint,
           scaled_channels,
           seed_everything,
)

__all__ = ["defaults", "fit", "group_batches", "field_groups", "freeze_norms", "evaluate", "save_checkpoint", "load_checkpoint",
           "scaled_channels", "seed_everything", "setup_distributed", "teardown_distributed",
           "resolve_device", "model_device", "to_device"]
