"""Small tensors made once and kept (per dtype and device, per sigma, ...): the rotation
conversions' constants, the supine matrix, the default joint limits, the blur's fixed kernels.

At batch 1 making such a tensor costs as much as the arithmetic it serves (docs/benchmarks.md,
session 57). A kept tensor must be made outside inference mode whichever mode the first call runs
in: an inference tensor cannot be saved for a later backward, so a first use under
`torch.inference_mode` (predict, the sampler) would break every gradient after it.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable
from typing import TypeVar

import torch

T = TypeVar("T")


def kept(store: dict, key: Hashable, make: Callable[[], T]) -> T:
    """store[key], made by `make()` outside inference mode on first use."""
    if key not in store:
        with torch.inference_mode(False):
            store[key] = make()
    return store[key]


__all__ = ["kept"]
