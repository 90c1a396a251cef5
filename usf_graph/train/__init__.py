"""Training and evaluation loops shared by all tasks."""

from .engine import (
                     evaluate,
                     fit,
                     load_checkpoint,
                     save_checkpoint,
                     seed_everything,
                     setup_distributed,
                     teardown_distributed,
)

__all__ = ["fit", "evaluate", "save_checkpoint", "load_checkpoint", "seed_everything",
           "setup_distributed", "teardown_distributed"]
