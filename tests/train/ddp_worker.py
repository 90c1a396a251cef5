"""One training step of a small spherical model, with and without batches drawn by group;
run alone (imported by the tests) or under torchrun."""

import json
import sys
from pathlib import Path

import torch
from torch.utils.data import TensorDataset

from usf_graph.models import SphericalClassifier
from usf_graph.train.devices import teardown_distributed
from usf_graph.train.engine import classification_step, fit

CASES = ("plain", "groups")


class NoNorm(SphericalClassifier):
    """BatchNorm statistics are per process under DDP; identity norms keep the step exact."""

    def __init__(self):
        super().__init__(level=2, channels=(4, 8), basis="gaussian", num_basis=3,
                         radius_spacings=3.0, readout="mean")
        self.norms = torch.nn.ModuleList(_Id() for _ in self.norms)
        self.jet_norm = _Id()
        self.pair_norms = torch.nn.ModuleList(_Id() for _ in self.pair_norms)


class _Id(torch.nn.Module):
    def forward(self, x, node_weight=None):
        return x


def step(case: str, seen: list | None = None) -> dict:
    """The state after one epoch of one (or two) steps, in float64: one process and two
    differ only in summation order. "groups": two batches of 4, each from one group (as of
    one field of view). ``seen`` gets the number of samples of each of this process's steps."""

    def counted(model, batch):
        out = classification_step(model, batch)
        if seen is not None:
            seen.append(out[2])
        return out

    dtype = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:
        torch.manual_seed(0)
        x = torch.randn(8, 162, 1)
        y = torch.arange(8) % 10
        model = NoNorm()
        groups = [0, 1, 1, 0, 1, 0, 0, 1] if case == "groups" else None
        fit(model, TensorDataset(x, y), epochs=1, batch_size=4 if groups else 8, progress=False,
            groups=groups, step=counted)
        return model.state_dict()
    finally:
        torch.set_default_dtype(dtype)


if __name__ == "__main__":
    import torch.distributed as dist

    for case in CASES:
        seen = []
        state = step(case, seen)
        rank = dist.get_rank() if dist.is_initialized() else 0
        world = dist.get_world_size() if dist.is_initialized() else 1
        (Path(sys.argv[1]) / f"{case}_{rank}.json").write_text(json.dumps({"world": world, "seen": seen}))
        if rank == 0:
            torch.save(state, Path(sys.argv[1]) / f"{case}.pt")
    teardown_distributed()
