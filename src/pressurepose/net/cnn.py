"""The two CNN trunks: the released PressureNet CNN (`paper`) and a CPU-sized one (`fast`).

paper (seed B.1, REFERENCE.md), input (B, C, 128, 54):
    Conv(C, 192, 7, s2, p3) tanh drop -> MaxPool(3, s2) -> Conv(192, 192, 3) tanh drop
    -> Conv(192, 384, 3) tanh drop -> Conv(384, 384, 3) tanh drop -> (384, 25, 7) -> Linear
~8.3 M parameters and ~0.56 GMAC per image: ~19 training images/s on 2 CPU cores.

fast (ours), input (B, C, 64, 27) - no upsampling, which adds no information:
    Conv(C, 32, 5, s2) -> Conv(32, 64, 3, s2) -> Conv(64, 128, 3, s2) -> Conv(128, 128, 3)
    each BatchNorm + SiLU -> (128, 8, 4) -> Linear 256, SiLU, dropout -> Linear
~1.3 M parameters and ~12 MMAC per image (~45x fewer). The stride-2 stem keeps full-
resolution activations (whose memory traffic, not arithmetic, dominated a CPU step) out of
the network; batch normalisation lets it train at lr 1e-3; the flattened 8 x 4 map keeps
where things are on the mat. Measured choices: docs/network.md.
"""

from __future__ import annotations

import torch
from torch import nn

ARCHS = ("paper", "fast")


class PaperCNN(nn.Module):
    def __init__(self, in_channels: int, out_features: int, dropout: float = 0.1) -> None:
        super().__init__()
        self.features = nn.Sequential(
            nn.Conv2d(in_channels, 192, 7, stride=2, padding=3),
            nn.Tanh(),
            nn.Dropout(dropout),
            nn.MaxPool2d(3, stride=2),
            nn.Conv2d(192, 192, 3),
            nn.Tanh(),
            nn.Dropout(dropout),
            nn.Conv2d(192, 384, 3),
            nn.Tanh(),
            nn.Dropout(dropout),
            nn.Conv2d(384, 384, 3),
            nn.Tanh(),
            nn.Dropout(dropout),
        )
        self.fc = nn.Linear(384 * 25 * 7, out_features)
        # Inputs are sums of 20,000 spread over ~600 taxels (tens per taxel) and contact 100:
        # as released, the first tanh sees them unscaled.

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, 128, 54) -> (B, out_features)."""
        return self.fc(self.features(x).flatten(1))


def _block(cin: int, cout: int, stride: int, kernel: int = 3) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, kernel, stride=stride, padding=kernel // 2, bias=False), nn.BatchNorm2d(cout), nn.SiLU()
    )


class FastCNN(nn.Module):
    # The released channel values (sums of 20,000, contact 100) are brought to O(1) first.
    INPUT_SCALE = 0.02

    def __init__(self, in_channels: int, out_features: int, dropout: float = 0.1, width: int = 1) -> None:
        super().__init__()
        c = 32 * width  # width multiplies every layer's channels (1: 1.3 M parameters, 2: ~5 M)
        self.features = nn.Sequential(
            _block(in_channels, c, 2, kernel=5),
            _block(c, 2 * c, 2),
            _block(2 * c, 4 * c, 2),
            _block(4 * c, 4 * c, 1),
        )
        self.fc = nn.Sequential(
            nn.Linear(4 * c * 8 * 4, 256 * width), nn.SiLU(), nn.Dropout(dropout), nn.Linear(256 * width, out_features)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, 64, 27) -> (B, out_features)."""
        return self.fc(self.features(x * self.INPUT_SCALE).flatten(1))


def make_cnn(arch: str, in_channels: int, out_features: int, dropout: float = 0.1, width: int = 1) -> nn.Module:
    if width < 1:
        raise ValueError(f"width must be >= 1, got {width}")
    if arch == "paper":
        if width != 1:
            raise ValueError("width applies to arch 'fast' only (the paper CNN is the released one)")
        net = PaperCNN(in_channels, out_features, dropout)
    elif arch == "fast":
        net = FastCNN(in_channels, out_features, dropout, width)
    else:
        raise ValueError(f"unknown arch {arch!r}; expected one of {', '.join(ARCHS)}")
    # Start at the reference output (raw = 0: mid-range shape and pose, supine, pelvis over
    # the mat centre) so early gradients are about the image, not about finding the bed.
    last = net.fc if isinstance(net.fc, nn.Linear) else net.fc[-1]
    with torch.no_grad():
        last.weight.mul_(0.1)
        last.bias.zero_()
    return net


def input_size(arch: str) -> tuple[int, int]:
    return (128, 54) if arch == "paper" else (64, 27)


__all__ = ["ARCHS", "FastCNN", "PaperCNN", "input_size", "make_cnn"]
