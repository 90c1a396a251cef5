"""Training and evaluation loops shared by all tasks."""

from .engine import (
                     defaults,
                     evaluate,
                     fit,
                     freeze_norms,
                     load_checkpoint,
                     save_checkpoint,
                     scaled_channels,
                     seed_everything,
                     setup_distributed,
                     teardown_distributed,
)

__all__ = ["defaults", "fit", "freeze_norms", "evaluate", "save_checkpoint", "load_checkpoint",
           "scaled_channels", "seed_everything", "setup_distributed", "teardown_distributed"]
