"""PressureNet: pressure image -> body parameters -> J24 joints, mesh and PMR maps (seed B.1-B.2).

Mod1: CNN on the pressure channels -> raw vector -> `ParamHead` -> BodyParams -> body model.
Mod2: a second CNN of the same arch on the pressure channels plus Mod1's reconstructed maps
(Q-hat, C-hat) predicts a residual added to Mod1's raw vector; its mesh goes through PMR again
for the Mod2 losses. With Mod1 frozen (`freeze_mod1`), Mod1 runs without gradients.

The body model is a submodule (so `.to(device)` moves it) but none of its tensors are part of
`trainable_state()`: a checkpoint holds only the CNNs.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import torch
from torch import nn

from pressurepose.body import BodyParams, load_body_model
from pressurepose.body.model import BodyModel
from pressurepose.errors import UserError
from pressurepose.mat import MatSpec
from pressurepose.net.cnn import make_cnn
from pressurepose.net.head import ParamHead
from pressurepose.net.heatmap import HeatmapNet, Localisation, flip_merged
from pressurepose.net.ik import IKConfig, fit_to_joints
from pressurepose.net.pmr import reconstruct_maps
from pressurepose.net.posture import roll_from_root, swapped_sides, to_swap
from pressurepose.net.preprocess import (
    check_pressure,
    constant_planes,
    pressure_channels,
    reconstruction_channels,
    smooth_loaded,
    upsample2,
)
from pressurepose.net.shift_test import SHIFT_TEST_ROWS, shift_merged, shift_stack
from pressurepose.net.stature import stature_from_joints

GENDER_UNKNOWN = 0.5  # Anny's gender phenotype: 0 male, 1 female


@dataclasses.dataclass(frozen=True)
class NetConfig:
    """What the network is; saved with every checkpoint (config.json)."""

    arch: Literal["paper", "fast", "heatmap"] = "fast"
    backend: Literal["anny", "smpl"] = "anny"
    modules: Literal[1, 2] = 1
    gender_input: bool = True  # gender given as an input (plane + Anny's gender entry)
    height_weight: bool = False  # height (m) and mass (/100 kg) given as constant planes
    smpl_dir: str | None = None  # SMPL model folder, backend smpl only
    dropout: float = 0.1  # the seed's dropout after every tanh (paper) / in the FC head (fast)
    width: int = 1  # channel multiplier (fast CNN 1.3 M parameters at 1; heatmap 0.43 M at 1, 1.5 M at 2)
    ik_steps: int = 3  # heatmap arch: IK steps fitting the body to the localised joints (eval only)
    # heatmap arch, eval only: also localise on the mirror image and average (net.heatmap.flip_merged);
    # twice the CNN's work per image.
    flip_test: bool = False
    # heatmap arch, eval only: also read the image moved a few rows along the bed and average the
    # joints moved back (net.shift_test); 5x the CNN's work per image.
    shift_test: bool = False
    # Smooth the reading within its loaded taxels first (sigma in taxels; 0: off), training and
    # inference alike: detail at the taxel scale out (net.preprocess.smooth_loaded).
    texture_sigma_taxels: float = 0.0
    # heatmap arch: a posture readout (supine / left / right / prone) on the pooled bottleneck
    # features (net.posture); the body's own posture is unchanged by it.
    posture_head: bool = False
    # heatmap arch: every stride-2 convolution reads its input low-passed (binomial 3 x 3), so the
    # subsampling is anti-aliased (net.heatmap.lowpass; training and inference alike).
    antialias: bool = False
    # heatmap arch with a posture head, eval only: where the body's posture and the readout's
    # differ by left and right alone, read the body again from its localised joints with left
    # and right exchanged, so that the body lies as the readout says (net.posture.to_swap).
    posture_consistent: bool = False
    # heatmap arch, eval only: the body's height parameter moved this share of the way to the
    # localised joints' bone-chain length (net.stature; 0: the regression head's height).
    stature_weight: float = 0.0
    # with stature_weight: the bone chain includes the head - neck link (False: from the neck down,
    # so a head end cut by the mat's edge or lengthened by a pillow does not enter; net.stature).
    stature_head: bool = True

    def __post_init__(self) -> None:
        if self.arch not in ("paper", "fast", "heatmap"):
            raise UserError(f"NetConfig.arch must be 'paper', 'fast' or 'heatmap', got {self.arch!r}")
        if self.arch == "heatmap" and self.modules != 1:
            raise UserError("NetConfig.arch 'heatmap' is one module (modules=1)")
        if self.flip_test and self.arch != "heatmap":
            raise UserError(
                f"the flip test is for arch 'heatmap' (its localised joints); this network is {self.arch!r}"
            )
        if self.shift_test and self.arch != "heatmap":
            raise UserError(
                f"the shift test is for arch 'heatmap' (its localised joints); this network is {self.arch!r}"
            )
        if self.posture_head and self.arch != "heatmap":
            raise UserError(f"the posture head is for arch 'heatmap'; this network is {self.arch!r}")
        if self.antialias and self.arch != "heatmap":
            raise UserError(f"anti-aliased subsampling is for arch 'heatmap'; this network is {self.arch!r}")
        if self.posture_consistent and not self.posture_head:
            raise UserError("posture_consistent needs a network with a posture head (train --posture-weight)")
        if not 0 <= self.ik_steps <= 50:
            raise UserError(f"NetConfig.ik_steps must lie in [0, 50], got {self.ik_steps}")
        if self.modules not in (1, 2):
            raise UserError(f"NetConfig.modules must be 1 or 2, got {self.modules!r}")
        if not 0 <= self.dropout < 1:
            raise UserError(f"NetConfig.dropout must lie in [0, 1), got {self.dropout}")
        if not 0 <= self.stature_weight <= 1:
            raise UserError(f"NetConfig.stature_weight must lie in [0, 1], got {self.stature_weight}")
        if self.stature_weight > 0 and (self.arch != "heatmap" or self.backend != "anny"):
            raise UserError(
                "NetConfig.stature_weight is for arch 'heatmap' on the Anny body model (its 'height' parameter)"
            )
        if not 0 <= self.texture_sigma_taxels <= 5:
            raise UserError(f"NetConfig.texture_sigma_taxels must lie in [0, 5], got {self.texture_sigma_taxels}")

    @property
    def in_channels(self) -> int:
        return 3 + 2 * self.height_weight + self.gender_input

    def load_body(self, dtype: torch.dtype = torch.float32, device="cpu") -> BodyModel:
        options = {"model_dir": self.smpl_dir} if self.backend == "smpl" else {}
        return load_body_model(self.backend, dtype=dtype, device=device, **options)


@dataclasses.dataclass(frozen=True)
class NetInputs:
    """A batch of network inputs. gender (B,) in [0, 1] (1 female, 0.5 unknown)."""

    pressure_mmhg: torch.Tensor  # (B, 64, 27)
    gender: torch.Tensor | None = None  # (B,)
    height_m: torch.Tensor | None = None  # (B,)
    mass_kg: torch.Tensor | None = None  # (B,)

    @property
    def batch_size(self) -> int:
        return self.pressure_mmhg.shape[0]


@dataclasses.dataclass(frozen=True)
class Estimate:
    """One module's estimate. Mesh and maps only when asked for (Mod1 training needs joints)."""

    raw: torch.Tensor  # (B, D) before unpacking
    params: BodyParams
    joints: torch.Tensor  # (B, 24, 3) mat frame, m
    vertices: torch.Tensor | None = None  # (B, V, 3)
    depth_mm: torch.Tensor | None = None  # (B, 64, 27) Q-hat
    contact: torch.Tensor | None = None  # (B, 64, 27) C-hat
    localisation: Localisation | None = None  # arch heatmap: the localised joints


class PressureNet(nn.Module):
    def __init__(self, config: NetConfig, body: BodyModel | None = None, mat: MatSpec | None = None) -> None:
        super().__init__()
        self.config = config
        self.mat = mat or MatSpec()
        self.body = body if body is not None else config.load_body()
        if self.body.name != config.backend:
            raise ValueError(f"body model is {self.body.name!r} but NetConfig.backend is {config.backend!r}")
        self.head = ParamHead(config.backend, self.body.shape_names, self.mat)
        D = self.head.size
        self.mod1 = (
            HeatmapNet(
                config.in_channels, D, self.mat, config.dropout, config.width, config.posture_head, config.antialias
            )
            if config.arch == "heatmap"
            else make_cnn(config.arch, config.in_channels, D, config.dropout, config.width)
        )
        self.mod2 = (
            make_cnn(config.arch, config.in_channels + 2, D, config.dropout, config.width)
            if config.modules == 2
            else None
        )
        if self.mod2 is not None:  # Mod2 starts as "no correction"
            last = self.mod2.fc if isinstance(self.mod2.fc, nn.Linear) else self.mod2.fc[-1]
            with torch.no_grad():
                last.weight.zero_()
        self.mod1_frozen = False
        self.readout_only = False

    @property
    def faces(self) -> torch.Tensor:
        return self.body.faces

    def freeze_mod1(self) -> None:
        """Train Mod2 on a fixed Mod1 (the seed trained the modules one after the other)."""
        self.mod1_frozen = True
        self.mod1.requires_grad_(False)

    def freeze_all_but_readout(self) -> None:
        """Train the posture readout alone on a fixed network (`train --posture-only`)."""
        if self.mod1.posture is None:
            raise ValueError("this network has no posture readout (NetConfig.posture_head)")
        self.readout_only = True
        self.requires_grad_(False)
        self.mod1.posture.requires_grad_(True)

    def train(self, mode: bool = True) -> PressureNet:
        super().train(mode)
        if self.mod1_frozen or self.readout_only:
            self.mod1.eval()  # no dropout / batch-statistics updates in the frozen module
        if self.readout_only:
            self.mod1.posture.train(mode)
        return self

    def trainable_state(self) -> dict[str, torch.Tensor]:
        """The CNN weights and buffers (not the body model's)."""
        return {k: v for k, v in self.state_dict().items() if not k.startswith("body.")}

    def load_trainable_state(self, state: dict[str, torch.Tensor]) -> None:
        missing, unexpected = self.load_state_dict(state, strict=False)
        missing = [k for k in missing if not k.startswith("body.")]
        if missing or unexpected:
            raise ValueError(
                f"checkpoint does not match the network: missing {missing[:5]}, unexpected {unexpected[:5]}"
            )

    # --- inputs -------------------------------------------------------------------------
    def channels(
        self, inputs: NetInputs, augment: bool = False, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """(B, C, 64, 27) Mod1 input channels (before any upsampling)."""
        check_pressure(inputs.pressure_mmhg)
        p = smooth_loaded(inputs.pressure_mmhg, self.config.texture_sigma_taxels)
        x = pressure_channels(p, augment, generator)
        extra = []
        if self.config.height_weight:
            if inputs.height_m is None or inputs.mass_kg is None:
                raise ValueError("this network takes height and mass as inputs; give height_m and mass_kg")
            extra += [inputs.height_m.reshape(-1), inputs.mass_kg.reshape(-1) / 100.0]
        if self.config.gender_input:
            extra.append(self._gender(inputs))
        if extra:
            x = torch.cat([x, constant_planes(torch.stack(extra, 1), x)], 1)
        return x

    def _gender(self, inputs: NetInputs) -> torch.Tensor:
        p = inputs.pressure_mmhg
        if inputs.gender is None:
            return torch.full((p.shape[0],), GENDER_UNKNOWN, dtype=p.dtype, device=p.device)
        return inputs.gender.to(p).reshape(-1)

    def _cnn(self, cnn: nn.Module, x: torch.Tensor) -> torch.Tensor:
        return cnn(upsample2(x) if self.config.arch == "paper" else x)

    # --- forward ------------------------------------------------------------------------
    def estimate(
        self,
        raw: torch.Tensor,
        gender: torch.Tensor | None,
        mesh: bool,
        maps: bool = True,
        params: BodyParams | None = None,
        localisation: Localisation | None = None,
    ) -> Estimate:
        """Unpack a raw vector (B, D) (unless `params` are given) and pose the body: joints
        only unless `mesh`; with the mesh, the PMR maps unless `maps` is False."""
        params = self.head(raw, gender) if params is None else params
        if not mesh:
            return Estimate(raw=raw, params=params, joints=self.body.joints(params), localisation=localisation)
        out = self.body(params)
        if not maps:
            return Estimate(raw=raw, params=params, joints=out.joints, vertices=out.vertices, localisation=localisation)
        maps = reconstruct_maps(out.vertices, out.faces, self.mat)
        return Estimate(
            raw=raw,
            params=params,
            joints=out.joints,
            vertices=out.vertices,
            depth_mm=maps.depth_mm,
            contact=maps.contact,
            localisation=localisation,
        )

    def _localise_and_fit(self, x: torch.Tensor, gender: torch.Tensor | None, mesh: bool, maps: bool) -> Estimate:
        """arch heatmap: localise the joints, regress the body, and (in eval mode) fit its
        joints to the localised ones by `ik_steps` IK steps (net/ik.py)."""
        if self.config.flip_test and not self.training:
            raw, loc = self.mod1(torch.cat([x, x.flip(-1)]))
            raw, loc = raw[: x.shape[0]], flip_merged(loc, self.mat.sensing_width_m)
        else:
            raw, loc = self.mod1(x)
        if self._shifting():  # x holds the shift test's copies (forward): one read of each image
            loc = shift_merged(loc, self.mat.pitch_row_m)
            raw = self.mod1.read_params(loc.joints, loc.features)
        params = self.head(raw, gender)
        if not self.training and self.config.posture_consistent:
            raw, loc, params = self._agree_with_readout(raw, loc, params, gender)
        if not self.training and self.config.stature_weight > 0:
            shape = stature_from_joints(
                self.body, params.shape, loc.joints, self.config.stature_weight, head=self.config.stature_head
            )
            params = params.replace(shape=shape)
        if not self.training and self.config.ik_steps > 0:
            ik = IKConfig(steps=self.config.ik_steps)
            params = fit_to_joints(self.body, params, loc.joints, ik.weights(loc.spread_m2), ik)
        return self.estimate(raw, gender, mesh, maps, params=params, localisation=loc)

    def _shifting(self) -> bool:
        return self.config.shift_test and not self.training  # NetConfig: arch heatmap only

    def _agree_with_readout(self, raw, loc: Localisation, params: BodyParams, gender):
        """Where the body lies supine and the readout says prone (or the sides likewise), the
        localised joints with left and right exchanged, the parameters read again from them."""
        swap = to_swap(roll_from_root(params.root_rotation.double()), loc.posture_logits)
        if not bool(swap.any()):
            return raw, loc, params
        pick = lambda a, b: torch.where(swap.reshape(-1, *[1] * (a.ndim - 1)), b, a)  # noqa: E731
        loc = dataclasses.replace(
            loc,
            joints=pick(loc.joints, swapped_sides(loc.joints)),
            grid_joints=pick(loc.grid_joints, swapped_sides(loc.grid_joints)),
            spread_m2=pick(loc.spread_m2, swapped_sides(loc.spread_m2)),
            logits=pick(loc.logits, swapped_sides(loc.logits)),
        )
        raw = pick(raw, self.mod1.read_params(loc.joints, loc.features))
        return raw, loc, self.head(raw, gender)

    def forward(
        self,
        inputs: NetInputs,
        augment: bool = False,
        generator: torch.Generator | None = None,
        mesh: bool = True,
        maps: bool = True,
    ) -> list[Estimate]:
        """[Mod1's estimate] or [Mod1's, Mod2's]. `mesh`: pose the final mesh; `maps`: and
        reconstruct its PMR maps (Mod1's mesh and maps are always made when Mod2 follows,
        since Mod2 reads them)."""
        gender = inputs.gender if self.config.gender_input else None
        if self._shifting():  # the shift test: the moved copies' channels from the moved images
            inputs = dataclasses.replace(inputs, pressure_mmhg=shift_stack(inputs.pressure_mmhg))
            inputs = _repeated(inputs, 1 + len(SHIFT_TEST_ROWS))
        x = self.channels(inputs, augment, generator)
        with torch.set_grad_enabled(torch.is_grad_enabled() and not self.mod1_frozen):
            if self.config.arch == "heatmap":
                return [self._localise_and_fit(x, gender, mesh, maps)]
            if self.mod2 is None:
                return [self.estimate(self._cnn(self.mod1, x), gender, mesh, maps)]
            est1 = self.estimate(self._cnn(self.mod1, x), gender, mesh=True)
        x2 = torch.cat([x, reconstruction_channels(est1.depth_mm.detach(), est1.contact.detach())], 1)
        raw2 = est1.raw + self._cnn(self.mod2, x2)
        return [est1, self.estimate(raw2, gender, mesh, maps)]


def _repeated(inputs: NetInputs, n: int) -> NetInputs:
    """`inputs` whose pressure already holds n copies of each batch, its per-image values
    (gender, height, mass) repeated to match."""
    rep = lambda v: None if v is None else v.repeat(n, *[1] * (v.ndim - 1))  # noqa: E731
    return dataclasses.replace(
        inputs, gender=rep(inputs.gender), height_m=rep(inputs.height_m), mass_kg=rep(inputs.mass_kg)
    )


__all__ = ["Estimate", "GENDER_UNKNOWN", "NetConfig", "NetInputs", "PressureNet"]
