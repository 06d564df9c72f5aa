"""HeatmapNet's convolutions without autograd on a CPU: batch norm folded into the weights and
each convolution, its bias and its SiLU one oneDNN call (`mkldnn._convolution_pointwise`, the
fused operator torch.compile emits); the 1x1 output convolution as a batched matrix product
that writes the maps in the (B, 4 J, H, W) layout `integral_joints` reads (a channels-last
convolution output would need a copy of the largest tensor). Same numbers as the modules to
float rounding (tests/test_heatmap.py); at batch 128 on one core ~15% less time for the
encoder-decoder (docs/benchmarks.md).

The folded weights are computed on first use and kept until a parameter or buffer changes
(in place or replaced), so training between evaluations is picked up.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

_CACHE = "_fused_weights"
# Set when the private oneDNN operator fails (another torch version's signature, a build without
# it): the modules run from then on (`fused_trunk` returns None once, `fusable` is False after).
_FAILED: list[str] = []


def fusable(net: nn.Module, x: torch.Tensor) -> bool:
    """Whether `fused_trunk` can run: eval mode, no autograd, float32 on a CPU with oneDNN."""
    return (
        not _FAILED
        and not net.training
        and not torch.is_grad_enabled()
        and x.device.type == "cpu"
        and x.dtype == torch.float32
        and torch.backends.mkldnn.enabled
        and torch.backends.mkldnn.is_available()
        and hasattr(torch.ops.mkldnn, "_convolution_pointwise")
    )


def _fold(block: nn.Sequential, scale: float = 1.0) -> tuple:
    """(weight, bias, padding, stride) of Conv2d (no bias) + BatchNorm2d (running stats), the
    input multiplied by `scale` folded in too."""
    conv, bn = block[0], block[1]
    s = bn.weight / torch.sqrt(bn.running_var + bn.eps)
    weight = (conv.weight * (s * scale)[:, None, None, None]).contiguous()
    return weight, bn.bias - bn.running_mean * s, list(conv.padding), list(conv.stride)


_SEQUENCES = ("enc1", "enc2", "enc3")  # folded block by block
_SINGLE = ("dec2", "squeeze", "dec1")  # one block each
_FOLDED = (*_SEQUENCES, *_SINGLE, "maps")  # every module the fold reads


def _key(net: nn.Module) -> tuple | None:
    """Each folded module's identity and its tensors' addresses and versions (reading the seven
    modules' own `_parameters` and `_buffers`: `net.parameters()` walks the whole module tree,
    0.3 ms per call at batch 1)."""
    key = []
    for name in _FOLDED:
        for module in getattr(net, name).modules():
            key.append(id(module))
            for t in (*module._parameters.values(), *module._buffers.values()):
                if t is None:
                    continue
                if t.is_inference():  # no version counter: fold every call
                    return None
                key.append((t.data_ptr(), t._version))
    return tuple(key)


def _weights(net: nn.Module) -> dict[str, list[tuple]]:
    key = _key(net)
    cached = net.__dict__.get(_CACHE)
    if cached is not None and key is not None and cached[0] == key:
        return cached[1]
    with torch.no_grad():
        folded = {name: [_fold(b) for b in getattr(net, name)] for name in _SEQUENCES}
        folded["enc1"][0] = _fold(net.enc1[0], net.INPUT_SCALE)
        folded.update({name: [_fold(getattr(net, name))] for name in _SINGLE})
        maps = net.maps
        folded["maps"] = [(maps.weight[:, :, 0, 0].contiguous(), maps.bias[:, None])]
    net.__dict__[_CACHE] = (key, folded)
    return folded


def _run(layers: list[tuple], x: torch.Tensor) -> torch.Tensor:
    for weight, bias, padding, stride in layers:
        x = torch.ops.mkldnn._convolution_pointwise(x, weight, bias, padding, stride, [1, 1], 1, "swish", [], None)
    return x


def fused_trunk(net: nn.Module, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
    """HeatmapNet's encoder-decoder on channels x (B, C, 64, 27): (bottleneck e3 (B, 96, 8, 4),
    maps (B, 4 J, 32, 14) contiguous), or None if the fused operator fails in this torch (the
    caller runs the modules; so does every later call). Call only when `fusable`."""
    try:
        return _fused(net, x)
    except (RuntimeError, TypeError, NotImplementedError) as exc:  # a private operator: may change
        _FAILED.append(f"{type(exc).__name__}: {exc}")
        return None


def _fused(net: nn.Module, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    w = _weights(net)
    e1 = _run(w["enc1"], net.subsampled(x.contiguous(memory_format=torch.channels_last)))
    e2 = _run(w["enc2"], net.subsampled(e1))
    e3 = _run(w["enc3"], net.subsampled(e2))
    d2 = _run(w["dec2"], torch.cat([F.interpolate(e3, size=e2.shape[-2:], mode="nearest"), e2], 1))
    up = F.interpolate(_run(w["squeeze"], d2), size=e1.shape[-2:], mode="nearest")
    d1 = _run(w["dec1"], torch.cat([up, e1], 1))  # (B, 32, H, W), channels last
    B, C, H, W = d1.shape
    weight, bias = w["maps"][0]
    pixels = d1.permute(0, 2, 3, 1).reshape(B, H * W, C).transpose(1, 2)  # (B, C, HW): a view when channels last
    maps = torch.baddbmm(bias.expand(B, -1, H * W), weight.expand(B, -1, -1), pixels)
    return e3, maps.view(B, -1, H, W)


__all__ = ["fusable", "fused_trunk"]
