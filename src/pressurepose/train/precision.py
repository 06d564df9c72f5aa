"""Training's --bf16: the heatmap encoder-decoder under bfloat16 autocast (docs/network.md).

The weights, Adam, the parameter head, the body model, the IK and the losses stay float32;
`HeatmapNet.trunk_dtype` is not saved, so the trained network is read in float32.
"""

from __future__ import annotations

import logging

import torch

from pressurepose.net.model import PressureNet

log = logging.getLogger(__name__)


def cpu_has_bf16() -> bool:
    """Whether oneDNN runs bfloat16 natively here (avx512_bf16 / AMX), not by emulation."""
    return torch.backends.mkldnn.is_available() and bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())


def train_in_bf16(net: PressureNet, device: torch.device) -> None:
    """Set the heatmap network's trunk to train under bfloat16 autocast; warn where it is emulated."""
    if device.type == "cpu" and not cpu_has_bf16():
        log.warning("--bf16: this CPU has no bfloat16 units (avx512_bf16 / AMX): training will be slower than float32")
    net.mod1.trunk_dtype = torch.bfloat16


__all__ = ["cpu_has_bf16", "train_in_bf16"]
