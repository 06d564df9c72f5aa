"""Weight averaging over the last epochs (`train --average-from EPOCH`).

The network's reading of real frames swings by up to 19 points of posture accuracy from one
epoch to the next while its synthetic error falls smoothly (docs/network.md, "The real-data
curve of one line"): the real frames sit near its decision boundaries, and which side of them
one epoch's weights fall on is chance. The equal average of the weights at the end of every
epoch from EPOCH on (Izmailov et al. 2018's stochastic weight averaging, here at the per-epoch
learning rate of the run) smooths that chance out. `torch.optim.swa_utils.AveragedModel` keeps
the average of every network module but the body model (fixed, and large); with
`use_buffers=True` the batch-norm running statistics are averaged with the weights, since they
were gathered on the augmented training stream that a pass of `update_bn` without the
augmentations would not reproduce.
"""

from __future__ import annotations

from contextlib import contextmanager

import torch
from torch import nn
from torch.optim.swa_utils import AveragedModel

from pressurepose.net.model import PressureNet

PREFIX = "average/"
COUNT = "average_count"


def _equal_average(average: torch.Tensor, current: torch.Tensor, count: torch.Tensor) -> torch.Tensor:
    """The running equal average; integer buffers (batch norm's batch counters) take the
    latest value (torch's own multi-tensor average divides them, which CUDA refuses)."""
    if not average.is_floating_point():
        return current
    return average + (current - average) / (count + 1).to(average.dtype)


class WeightAverage:
    """The running equal average of a network's trainable state (all but `body`)."""

    def __init__(self, net: PressureNet) -> None:
        self.modules = nn.ModuleDict({name: m for name, m in net.named_children() if name != "body"})
        self.average = AveragedModel(self.modules, avg_fn=_equal_average, use_buffers=True)

    @property
    def count(self) -> int:
        return int(self.average.n_averaged)

    def update(self) -> None:
        """Add the network's current weights to the average."""
        self.average.update_parameters(self.modules)

    def state(self) -> dict[str, torch.Tensor]:
        """The averaged trainable state, named as `PressureNet.trainable_state()` names it."""
        return dict(self.average.module.state_dict())

    def tensors(self) -> dict[str, torch.Tensor]:
        """For the checkpoint: the averaged state under "average/" and the number averaged."""
        return {**{PREFIX + k: v for k, v in self.state().items()}, COUNT: self.average.n_averaged.clone()}

    def load(self, tensors: dict[str, torch.Tensor]) -> None:
        """Restore from `tensors()`; the shapes are checked by the caller."""
        self.average.module.load_state_dict({k[len(PREFIX) :]: v for k, v in tensors.items() if k.startswith(PREFIX)})
        self.average.n_averaged.copy_(tensors[COUNT])

    @contextmanager
    def swapped_in(self, net: PressureNet):
        """Within the block the network holds the averaged weights; its own come back after."""
        own = {k: v.clone() for k, v in net.trainable_state().items()}
        net.load_trainable_state(self.state())
        try:
            yield net
        finally:
            net.load_trainable_state(own)


__all__ = ["COUNT", "PREFIX", "WeightAverage"]
