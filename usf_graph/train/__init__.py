"""Training and evaluation loops shared by all tasks."""

from .engine import (
                     evaluate,
                     fit,
                     freeze_norms,
                     load_checkpoint,
                     save_checkpoint,
                     seed_everything,
                     setup_distributed,
                     teardown_distributed,
)

__all__ = ["fit", "freeze_norms", "evaluate", "save_checkpoint", "load_checkpoint", "seed_everything",
           "setup_distributed", "teardown_distributed"]
