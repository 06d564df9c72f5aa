"""The limb-localising network (`arch=heatmap`): per-joint heatmaps on the mat grid, integral
regression of every J24 joint, and body parameters from a head conditioned on those joints.

Pressure channels (B, C, 64, 27) -> a small fully convolutional encoder-decoder (U-Net shape):

    stem   Conv(C, 32, 5, s2), Conv(32, 48, 3)    32 x 14
    enc2   Conv(48, 64, 3, s2), Conv(64, 64, 3)   16 x 7
    enc3   Conv(64, 96, 3, s2), Conv(96, 96, 3)    8 x 4   (sees the whole image: sides, posture)
    dec2   up(enc3) ++ enc2 -> Conv 64             16 x 7
    dec1   up(Conv1x1(dec2) 24) ++ stem -> Conv 32 32 x 14
    out    Conv1x1 -> 4 maps per joint: logit, offset along, offset across, height

every conv with batch norm and SiLU (~40 MMAC per image, 3x the fast CNN; a full-resolution
stem and wider decoder cost 100 MMAC for no gain we could afford to measure). Heatmaps live on
the 32 x 14 half-resolution grid: integral regression reads positions between cells. Per joint j, with s = softmax(logit_j) over the 32 x 14
cells (centres g_p in the mat frame, metres):

    (x, y)_j = sum_p s_p (g_p + OFFSET_SCALE_M * offset_p)     integral (soft-argmax) regression
    z_j      = sum_p s_p  HEIGHT_SCALE_M * height_p + HEIGHT_BIAS_M

The offsets let joints lie off the sensing area (hands over the bed's side) and between cells;
an auxiliary cross-entropy against a Gaussian (sigma HEATMAP_SIGMA_M) at the true position,
clamped onto the grid, keeps the heatmap itself on the joint and gives every cell a gradient
(with the integral loss alone, 17 epochs on 860 images left the joints ~24 cm off). `spread_m2` is the heatmap's variance about its mean: a confidence for the fit.
With `antialias` (`NetConfig.antialias`, `train --antialias`) each stride-2 convolution reads its
input through a fixed binomial 3 x 3 low-pass first (`lowpass`): the convolution is linear, so
this is (away from the border) the convolution's output blurred before it is sampled at every other cell - the
anti-aliased subsampling of Zhang, "Making convolutional networks shift-invariant again" (ICML
2019) - and a body moved a row or two reads more nearly the same (docs/network.md
"Anti-aliased subsampling").
The parameter head is an MLP on the localised joints (detached: it reads them, it does not
move them) and the pooled bottleneck features; its raw vector goes through the usual
`ParamHead` (joint-limit squash, 6D root rotation).
"""

from __future__ import annotations

import dataclasses

import torch
import torch.nn.functional as F
from torch import nn

from pressurepose.body.joints import J24_MIRROR, NUM_JOINTS, mirror_joints
from pressurepose.mat import MatSpec
from pressurepose.net.heatmap_fused import fusable, fused_trunk
from pressurepose.net.losses import JOINT_SCALE_M
from pressurepose.net.posture import PostureHead, mirrored_logits

OFFSET_SCALE_M = 0.1
HEIGHT_SCALE_M = 0.1
HEIGHT_BIAS_M = 0.1
HEATMAP_LOSS_WEIGHT = 0.5
HEATMAP_SIGMA_M = 0.05
MAPS_PER_JOINT = 4  # logit, offset x, offset y, height


@dataclasses.dataclass(frozen=True)
class Localisation:
    """Where the heatmaps put the J24 joints (mat frame, metres)."""

    joints: torch.Tensor  # (B, 24, 3) integral regression, offsets and height included
    grid_joints: torch.Tensor  # (B, 24, 2) soft-argmax of the heatmap alone (x, y)
    spread_m2: torch.Tensor  # (B, 24) variance of the heatmap about grid_joints
    logits: torch.Tensor  # (B, 24, H, W) the heatmaps' logits
    centres: torch.Tensor  # (H, W, 2) the cells' (x, y)
    posture_logits: torch.Tensor | None = None  # (B, 4) over net.posture.POSTURES, with a posture head
    features: torch.Tensor | None = None  # (B, F) the pooled bottleneck the heads read

    @property
    def spread_m(self) -> torch.Tensor:
        """(B, 24) each heatmap's spread on the mat: the RMS distance of its probability from its
        mean, sqrt(spread_m2) (docs/network.md "How far to trust a joint")."""
        return self.spread_m2.clamp_min(0).sqrt()

    @property
    def log_prob(self) -> torch.Tensor:
        """(B, 24, H, W) log-softmax of the heatmaps (for the loss; not computed at inference)."""
        B, J, H, W = self.logits.shape
        return torch.log_softmax(self.logits.reshape(B, J, H * W), -1).reshape(B, J, H, W)


def soft_argmax(logits: torch.Tensor, centres: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Integral regression over a grid.

    logits: (B, J, H, W); centres: (H, W, 2) cell positions. Returns the expected position
    (B, J, 2) under softmax(logits) over the H x W cells, and the variance about it (B, J)
    (summed over both coordinates)."""
    if logits.ndim != 4 or centres.shape != (*logits.shape[2:], 2):
        raise ValueError(
            f"logits (B, J, H, W) and centres (H, W, 2) must agree, got {tuple(logits.shape)} "
            f"and {tuple(centres.shape)}"
        )
    B, J, H, W = logits.shape
    return _moments(torch.softmax(logits.reshape(B, J, H * W), -1), centres)


def _moments(prob: torch.Tensor, centres: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean (B, J, 2) and variance (B, J) of the cell centres under prob (B, J, HW)."""
    c = centres.reshape(-1, 2).to(prob)
    mean = prob @ c  # (B, J, 2)
    second = prob @ c.square()
    return mean, (second - mean.square()).sum(-1).clamp(min=0.0)


def integral_joints(maps: torch.Tensor, centres: torch.Tensor) -> Localisation:
    """maps (B, J, 4, H, W): logit, offset x, offset y, height per joint -> Localisation."""
    if maps.ndim != 5 or maps.shape[2] != MAPS_PER_JOINT:
        raise ValueError(f"maps must have shape (B, J, {MAPS_PER_JOINT}, H, W), got {tuple(maps.shape)}")
    B, J, _, H, W = maps.shape
    logits = maps[:, :, 0]
    if centres.shape != (H, W, 2):
        raise ValueError(f"centres must have shape ({H}, {W}, 2), got {tuple(centres.shape)}")
    prob = torch.softmax(logits.reshape(B, J, H * W), -1)  # one softmax for the position and the rest
    grid, spread = _moments(prob, centres)
    extra = (maps[:, :, 1:].reshape(B, J, 3, H * W) @ prob[..., None])[..., 0]  # (B, J, 3)
    xy = grid + OFFSET_SCALE_M * extra[..., :2]
    z = HEIGHT_SCALE_M * extra[..., 2:] + HEIGHT_BIAS_M
    return Localisation(
        joints=torch.cat([xy, z], -1),
        grid_joints=grid,
        spread_m2=spread,
        logits=logits,
        centres=centres,
    )


def flip_merged(loc: Localisation, width_m: float) -> Localisation:
    """The flip test's localisation: `loc` holds 2B images, the first B as given and the last B
    their mirror images (columns reversed). The mirrored half is mapped back - joints reflected
    across the mat's centre line (y -> W - y, W the sensing width) with left and right swapped
    (J24_MIRROR), the heatmaps flipped, left and right postures swapped - and averaged with the
    first half: each joint's position, height, heatmap variance and logits, the posture logits
    (the features are the image's own, for the parameter head). The mirror image of a body's image is the image of the
    mirrored body (the bed and the simulation are mirror symmetric), so both halves estimate
    the same joints and their mean has less of either's error. The heatmaps' column c is the
    mirror image of column W_cells - 1 - c: the cell centres are symmetric about the centre line
    and the stride-2 stem maps input column 2c to output c, so mirrored input column 26 - 2c to
    13 - c (docs/network.md "Flip test, IK settings and occlusion")."""
    B = loc.joints.shape[0] // 2
    perm = list(J24_MIRROR)
    mean = lambda a, b: (a + b) / 2  # noqa: E731
    return Localisation(
        joints=mean(loc.joints[:B], mirror_joints(loc.joints[B:], width_m)),
        grid_joints=mean(loc.grid_joints[:B], mirror_joints(loc.grid_joints[B:], width_m)),
        spread_m2=mean(loc.spread_m2[:B], loc.spread_m2[B:, perm]),
        logits=mean(loc.logits[:B], loc.logits[B:, perm].flip(-1)),
        centres=loc.centres,
        posture_logits=None
        if loc.posture_logits is None
        else mean(loc.posture_logits[:B], mirrored_logits(loc.posture_logits[B:])),
        features=None if loc.features is None else loc.features[:B],
    )


def cell_centres(mat: MatSpec, rows: int, cols: int) -> torch.Tensor:
    """(rows, cols, 2) mat-frame (x, y) centres of a rows x cols grid over the sensing area."""
    r = (torch.arange(rows, dtype=torch.float64) + 0.5) * (mat.sensing_length_m / rows)
    c = (torch.arange(cols, dtype=torch.float64) + 0.5) * (mat.sensing_width_m / cols)
    rr, cc = torch.meshgrid(r, c, indexing="ij")
    return torch.stack([rr, cc], -1)


def binomial_kernel(dtype: torch.dtype = torch.float32, device=None) -> torch.Tensor:
    """(3, 3) the binomial low-pass: [1, 2, 1] / 4 along each axis (sums to 1)."""
    k = torch.tensor([0.25, 0.5, 0.25], dtype=dtype, device=device)
    return k[:, None] * k[None, :]


def lowpass(x: torch.Tensor, kernel: torch.Tensor | None = None) -> torch.Tensor:
    """Each channel of x (B, C, H, W) blurred by `binomial_kernel`, zero padding, stride 1: the
    sum over the image kept away from its border. kernel: that kernel in x's dtype and device,
    if kept (else made)."""
    kernel = binomial_kernel(x.dtype, x.device) if kernel is None else kernel
    C = x.shape[1]
    return F.conv2d(x, kernel.expand(C, 1, 3, 3).contiguous(), padding=1, groups=C)


def _conv(cin: int, cout: int, stride: int = 1, kernel: int = 3) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, kernel, stride=stride, padding=kernel // 2, bias=False), nn.BatchNorm2d(cout), nn.SiLU()
    )


class HeatmapNet(nn.Module):
    """(B, C, 64, 27) channels -> (raw (B, D), Localisation). See the module doc."""

    INPUT_SCALE = 0.02  # the released channel values (sums of 20,000, contact 100) -> O(1)
    EVAL_CHUNK = 64  # eval batches run in pieces this size: activations stay in cache (~15% at 128)

    def __init__(
        self,
        in_channels: int,
        out_features: int,
        mat: MatSpec | None = None,
        dropout: float = 0.1,
        width: int = 1,
        posture: bool = False,
        antialias: bool = False,
    ) -> None:
        super().__init__()
        mat = mat or MatSpec()
        self.antialias = antialias
        self.trunk_dtype: torch.dtype | None = None  # training's --bf16 (not saved: use is float32)
        c = [32 * width, 48 * width, 64 * width, 96 * width, 24 * width]
        self.enc1 = nn.Sequential(_conv(in_channels, c[0], 2, kernel=5), _conv(c[0], c[1]))
        self.enc2 = nn.Sequential(_conv(c[1], c[2], 2), _conv(c[2], c[2]))
        self.enc3 = nn.Sequential(_conv(c[2], c[3], 2), _conv(c[3], c[3]))
        self.dec2 = _conv(c[3] + c[2], c[2])
        self.squeeze = _conv(c[2], c[4], kernel=1)
        self.dec1 = _conv(c[4] + c[1], c[0])
        self.maps = nn.Conv2d(c[0], NUM_JOINTS * MAPS_PER_JOINT, 1)
        with torch.no_grad():  # start with flat heatmaps, no offsets, joints at HEIGHT_BIAS_M
            self.maps.weight.mul_(0.1)
            self.maps.bias.zero_()
        rows, cols = (mat.rows + 1) // 2, (mat.cols + 1) // 2
        self.register_buffer("centres", cell_centres(mat, rows, cols).float(), persistent=False)
        self.register_buffer("joint_origin", torch.tensor([*mat.centre_m, 0.1]).float(), persistent=False)
        self.register_buffer("lowpass_kernel", binomial_kernel(), persistent=False)
        self.fc = nn.Sequential(
            nn.Linear(NUM_JOINTS * 3 + 2 * c[3], 256), nn.SiLU(), nn.Dropout(dropout), nn.Linear(256, out_features)
        )
        with torch.no_grad():  # the reference body at the start (as make_cnn does)
            self.fc[-1].weight.mul_(0.1)
            self.fc[-1].bias.zero_()
        self.posture = PostureHead(2 * c[3]) if posture else None  # net/posture.py

    def _trunk(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The encoder-decoder by the modules: (bottleneck e3, maps (B, 4 J, H, W)) in float32;
        without autograd on a CPU `heatmap_fused.fused_trunk` computes the same faster. With
        `trunk_dtype` set (training's --bf16) its convolutions run in training mode under
        autocast to that dtype."""
        if self.trunk_dtype is None or not self.training:
            return self._trunk_layers(x)
        with torch.autocast(x.device.type, dtype=self.trunk_dtype):
            e3, maps = self._trunk_layers(x)
        return e3.float(), maps.float()

    def _trunk_layers(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        # mkldnn's convolutions in channels-last: ~20% faster at batch 128 in eval, 7-10% per
        # training step (docs/benchmarks.md "Session 55")
        x = x.contiguous(memory_format=torch.channels_last)
        e1 = self.enc1(self.subsampled(x * self.INPUT_SCALE))  # (B, 48, 32, 14)
        e2 = self.enc2(self.subsampled(e1))  # (B, 64, 16, 7)
        e3 = self.enc3(self.subsampled(e2))  # (B, 96, 8, 4)
        up = lambda a, like: F.interpolate(a, size=like.shape[-2:], mode="nearest")  # noqa: E731
        d2 = self.dec2(torch.cat([up(e3, e2), e2], 1))  # (B, 64, 16, 7)
        d1 = self.dec1(torch.cat([up(self.squeeze(d2), e1), e1], 1))  # (B, 32, 32, 14)
        return e3, self.maps(d1)

    def subsampled(self, x: torch.Tensor) -> torch.Tensor:
        """What a stride-2 block reads: x, low-passed when the network is anti-aliased."""
        return lowpass(x, self.lowpass_kernel.to(x.dtype)) if self.antialias else x

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, Localisation]:
        if not self.training and x.shape[0] > self.EVAL_CHUNK:  # exact: batch norm uses running stats
            parts = [self.forward(c) for c in x.split(self.EVAL_CHUNK)]
            cat = lambda name: torch.cat([getattr(loc, name) for _, loc in parts])  # noqa: E731
            posture = cat("posture_logits") if self.posture is not None else None
            loc = Localisation(
                cat("joints"),
                cat("grid_joints"),
                cat("spread_m2"),
                cat("logits"),
                self.centres,
                posture,
                cat("features"),
            )
            return torch.cat([raw for raw, _ in parts]), loc
        B = x.shape[0]
        fused = fused_trunk(self, x) if fusable(self, x) else None
        e3, maps = fused if fused is not None else self._trunk(x)
        loc = integral_joints(maps.reshape(B, NUM_JOINTS, MAPS_PER_JOINT, *maps.shape[-2:]), self.centres)
        pooled = torch.cat([e3.mean((-2, -1)), e3.amax((-2, -1))], 1)  # (B, 192)
        posture = self.posture(pooled) if self.posture is not None else None
        loc = dataclasses.replace(loc, posture_logits=posture, features=pooled)
        return self.read_params(loc.joints, pooled), loc

    def read_params(self, joints: torch.Tensor, pooled: torch.Tensor) -> torch.Tensor:
        """The parameter head: raw (B, D) from localised joints (B, 24, 3) and pooled features."""
        rel = (joints.detach() - self.joint_origin) / JOINT_SCALE_M  # (B, 24, 3)
        return self.fc(torch.cat([rel.flatten(1), pooled], 1))


def localisation_loss(
    loc: Localisation, joints: torch.Tensor, mat: MatSpec | None = None
) -> tuple[torch.Tensor, dict[str, float]]:
    """Mean Euclidean error of the localised joints / JOINT_SCALE_M, plus HEATMAP_LOSS_WEIGHT x
    the cross-entropy of the heatmaps against Gaussians (sigma HEATMAP_SIGMA_M) at the true
    (x, y) clamped onto the sensing area (a joint off the mat is drawn to the nearest edge
    cell; its offset does the rest). joints (B, 24, 3) true, mat frame."""
    mat = mat or MatSpec()
    true = joints.to(loc.joints)
    located = (loc.joints - true).norm(dim=-1).mean() / JOINT_SCALE_M
    lo = true.new_tensor([0.0, 0.0])
    hi = true.new_tensor([mat.sensing_length_m, mat.sensing_width_m])
    target = torch.minimum(torch.maximum(true[..., :2], lo), hi)  # (B, J, 2)
    d2 = (loc.centres.to(true)[None, None] - target[:, :, None, None]).square().sum(-1)  # (B, J, H, W)
    gauss = torch.softmax(-d2.flatten(2) / (2 * HEATMAP_SIGMA_M**2), -1)
    heatmap = -(gauss * loc.log_prob.flatten(2)).sum(-1).mean()
    total = located + HEATMAP_LOSS_WEIGHT * heatmap
    return total, {"localised": float(located.detach()), "heatmap": float(heatmap.detach())}


__all__ = [
    "HeatmapNet",
    "Localisation",
    "binomial_kernel",
    "cell_centres",
    "flip_merged",
    "integral_joints",
    "localisation_loss",
    "lowpass",
    "soft_argmax",
]
