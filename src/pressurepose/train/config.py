"""Training configuration: one frozen dataclass, presets for the usual runs.

`preset` fills every field left at None: "paper" is the seed's setup (the released CNN, Adam,
lr 2e-5, weight decay 5e-4, batch 128, 100 epochs - B.3); "fast" is our CPU network, which
trains at lr 1e-3 thanks to batch normalisation; "smoke" is a two-epoch run on small batches
to check that everything runs. Explicit fields win over the preset.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Literal

from pressurepose.errors import UserError

PRESETS: dict[str, dict] = {
    "paper": {"arch": "paper", "epochs": 100, "batch_size": 128, "lr": 2e-5, "weight_decay": 5e-4},
    "fast": {"arch": "fast", "epochs": 100, "batch_size": 128, "lr": 1e-3, "weight_decay": 5e-4},
    "smoke": {"arch": "fast", "epochs": 2, "batch_size": 16, "lr": 1e-3, "weight_decay": 5e-4},
}


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """`pressurepose train`: train Mod1 (or Mod2 on a trained Mod1) and write RUN/.

    Args:
        data: dataset folder (generated shards with manifest.json, or *.npz files; docs/network.md).
        out: run folder: config.json, checkpoint.safetensors, model.safetensors, metrics.jsonl,
            metrics.csv, metrics.png. An existing run there is resumed.
        module: 1 trains Mod1; 2 trains Mod2 on the frozen Mod1 of the run given by `mod1`.
        mod1: the Mod1 run folder (module 2 only).
        preset: fills the fields left unset: paper (seed B.3), fast (CPU network), smoke.
        arch: paper (the released CNN, 128 x 54 input), fast (ours, 64 x 27) or heatmap (per-joint
            heatmaps, integral regression, a parameter head on the localised joints, IK; docs/network.md).
        backend: body model: anny (embedded) or smpl (needs smpl_dir).
        smpl_dir: folder of the SMPL model file (backend smpl).
        epochs: total epochs (a resumed run continues up to this).
        batch_size: images per step.
        lr: Adam learning rate.
        weight_decay: Adam weight decay.
        augment: the seed's calibration noise on training images.
        gender_input: give the gender as an input (as the original did).
        height_weight: give height and mass as input planes.
        dropout: dropout rate (the seed's 0.1).
        width: channel multiplier of the network (fast CNN: 1.3 M parameters at 1, ~5 M at 2; heatmap:
            0.43 M at 1, 1.5 M at 2).
        shift_rows: augmentation: move training images (and labels) by up to this many rows along the bed.
        shift_cols: augmentation: the same across the bed, in columns.
        mirror: augmentation: share of training images mirrored left-right with their labels
            (left and right joints swapped; `train.augment.mirror_batch`; 0 = off).
        bands: augmentation: share of training images read through an air-cell mattress's
            transverse bands (rows alternately brighter and darker; `train.augment.bands_batch`; 0 = off).
        repress: augmentation: share of training images re-pressed into a random other mattress
            from their depth labels (deeper sinking, another pressure law and spread; the force
            kept): real mats read far more uniform pressure than the calibrated simulation, most
            of all under side-lying people (0 = off; `train.augment.repress_batch`).
        pillow: augmentation: share of training images whose head rests on a pillow (the head's
            load spread over a broad patch reaching beyond the head; `train.augment.pillow_batch`; 0 = off).
        texture: augmentation: share of training images read through a mat of uneven gain (random
            per-row and per-taxel log-normal gains, the force kept; `train.augment.texture_batch`; 0 = off).
        flatten: augmentation: share of training images whose contrast is flattened (each loaded
            taxel's reading raised to a power in [0, 1], the total kept; `train.augment.flatten_batch`; 0 = off).
        spread: augmentation: share of training images read through a mat that spreads the load
            (a Gaussian of 0.5-2 taxels, then a reading floor of 1-4 mmHg, the force kept;
            `train.augment.spread_batch`; 0 = off).
        occlude: augmentation: share of training images with one band of 2-8 loaded rows zeroed
            (the labels kept), so that no single band decides the answer (`train.augment.occlude_batch`; 0 = off).
        speckle: augmentation: share of training images with stray readings off the body (0-8 spots
            of one or two taxels at 3.3-15 mmHg, the labels kept; `train.augment.speckle_batch`; 0 = off).
        texture_sigma: the network smooths every reading within its loaded taxels by a Gaussian of
            this many taxels before its channels, in training and in use (detail at the taxel scale
            out, the outline kept; `net.preprocess.smooth_loaded`; 0 = off).
        antialias: arch heatmap: every stride-2 convolution reads its input through a binomial
            3 x 3 low-pass, so the subsampling is anti-aliased and a body moved a row or two reads
            more nearly the same (`NetConfig.antialias`, `net.heatmap.lowpass`). With --init a network
            that has it keeps it (--no-antialias does not switch it off), and --antialias switches
            it on for one that lacks it.
        bf16: arch heatmap: run the encoder-decoder's forward and backward under bfloat16 autocast
            (weights, optimiser, losses, body model and IK stay float32; validation and use are
            float32). On a CPU with bfloat16 units (avx512_bf16 / AMX) 2.1x the bare training step and
            1.47x the epoch with augmentations; slower without them (a warning says so).
            docs/benchmarks.md "Session 65".
        average_from: average the weights (batch-norm statistics included) at the end of every epoch
            from this one on; model.safetensors then holds the average and last/model.safetensors the
            last epoch's weights (`train.average`; 0 = off).
        posture_weight: arch heatmap: give the network a posture readout (supine / left / right /
            prone from its pooled features; `net.posture`) trained with this weight on its
            cross-entropy (0 = no readout, unless posture_only).
        posture_only: train the posture readout alone on the frozen network of `init` (which may
            have none yet); the loss is the posture's cross-entropy.
        lr_gamma: learning-rate decay per epoch: epoch e trains at lr * lr_gamma^(e-1) (1 = constant).
        init: start from the weights of this run's network (fine-tuning; the same network settings);
            Adam's state starts fresh. "default" = the packaged model.
        stature_weight: arch heatmap on Anny, how the trained network is read (inference only):
            move the body's height parameter this share of the way to the localised joints'
            bone-chain length (`NetConfig.stature_weight`, net.stature; the packaged model's 0.194).
            Not given: 0 from random weights, the other network's with --init.
        synthesis_weight: Mod2 only: weight of the analysis-by-synthesis loss (sim #2 pressure of
            the estimated mesh vs the input; 0 = off; slow: ~15 ms a sample).
        val_fraction: share of the samples held out for per-epoch validation.
        seed: seeds the split, the order, the augmentation and dropout of every epoch.
        device: auto (CUDA when present), cpu or cuda.
        num_workers: DataLoader worker processes.
        in_memory: decode the training samples into memory once before the first epoch (a
            generated dataset's shards read in random order cost as much as the training step;
            ~21 KB per sample, ~1 GB per 48,000); --no-in-memory for data larger than the memory.
        progress: show a progress bar.
        save_every: epochs between checkpoints, metrics files and plot (the last epoch always).
    """

    data: Path | None = None
    out: Path = Path("out/train")
    module: Literal[1, 2] = 1
    mod1: Path | None = None
    preset: Literal["paper", "fast", "smoke"] = "paper"
    arch: Literal["paper", "fast", "heatmap"] | None = None
    backend: Literal["anny", "smpl"] = "anny"
    smpl_dir: str | None = None
    epochs: int | None = None
    batch_size: int | None = None
    lr: float | None = None
    weight_decay: float | None = None
    augment: bool = True
    gender_input: bool = True
    height_weight: bool = False
    dropout: float = 0.1
    width: int = 1
    shift_rows: int = 0
    shift_cols: int = 0
    mirror: float = 0.0
    repress: float = 0.0
    bands: float = 0.0
    pillow: float = 0.0
    texture: float = 0.0
    occlude: float = 0.0
    speckle: float = 0.0
    flatten: float = 0.0
    spread: float = 0.0
    texture_sigma: float = 0.0
    antialias: bool = False
    bf16: bool = False
    lr_gamma: float = 1.0
    average_from: int = 0
    posture_weight: float = 0.0
    posture_only: bool = False
    init: Path | None = None
    stature_weight: float | None = None
    synthesis_weight: float = 0.0
    val_fraction: float = 0.05
    seed: int = 0
    device: Literal["auto", "cpu", "cuda"] = "auto"
    num_workers: int = 0
    in_memory: bool = True
    progress: bool = True
    save_every: int = 1

    @classmethod
    def paper(cls, **changes) -> TrainConfig:
        return cls(preset="paper", **changes).resolved()

    @classmethod
    def fast(cls, **changes) -> TrainConfig:
        return cls(preset="fast", **changes).resolved()

    @classmethod
    def smoke(cls, **changes) -> TrainConfig:
        return cls(preset="smoke", **changes).resolved()

    def resolved(self) -> TrainConfig:
        """The config with every None filled from the preset, checked."""
        if self.preset not in PRESETS:
            raise UserError(f"unknown preset {self.preset!r}; expected one of {', '.join(PRESETS)}")
        filled = {k: v for k, v in PRESETS[self.preset].items() if getattr(self, k) is None}
        cfg = dataclasses.replace(self, **filled)
        cfg._check()
        return cfg

    def _check(self) -> None:
        if self.module not in (1, 2):
            raise UserError(f"module must be 1 or 2, got {self.module}")
        if self.module == 2 and self.arch == "heatmap":
            raise UserError("arch heatmap is one module (it fits the body to its localised joints): use --module 1")
        if self.module == 2 and self.mod1 is None:
            raise UserError("module 2 trains on a trained Mod1: give --mod1 RUN (a `--module 1` run folder)")
        for name in ("epochs", "batch_size", "save_every"):
            if getattr(self, name) < 1:
                raise UserError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not self.lr > 0 or self.weight_decay < 0:
            raise UserError(f"lr must be > 0 and weight_decay >= 0, got {self.lr}, {self.weight_decay}")
        if not (0 <= self.shift_rows < 64 and 0 <= self.shift_cols < 27):
            raise UserError(
                f"shift_rows must lie in [0, 64) and shift_cols in [0, 27), got {self.shift_rows}, {self.shift_cols}"
            )
        for name in ("mirror", "repress", "bands", "pillow", "texture", "occlude", "speckle", "flatten", "spread"):
            if not 0 <= getattr(self, name) <= 1:
                raise UserError(f"{name} must lie in [0, 1] (a share of the images), got {getattr(self, name)}")
        if not 0 <= self.dropout < 1:
            raise UserError(f"dropout must lie in [0, 1), got {self.dropout}")
        if self.occlude > 0 and self.synthesis_weight > 0:
            raise UserError(
                "--occlude and --synthesis-weight do not combine: the synthesis loss would fit the "
                "body to the occluded image; give one of them"
            )
        if not 0 <= self.texture_sigma <= 5:
            raise UserError(f"texture_sigma must lie in [0, 5] taxels, got {self.texture_sigma}")
        if self.posture_weight < 0:
            raise UserError(f"posture_weight must be >= 0, got {self.posture_weight}")
        if self.antialias and self.arch != "heatmap":
            raise UserError(f"--antialias is for --arch heatmap; this run is --arch {self.arch}")
        if self.bf16 and self.arch != "heatmap":
            raise UserError(f"--bf16 is for --arch heatmap; this run is --arch {self.arch}")
        if (self.posture_weight > 0 or self.posture_only) and self.arch != "heatmap":
            raise UserError(f"the posture readout is for --arch heatmap; this run is --arch {self.arch}")
        if self.posture_only and (self.init is None or self.posture_weight > 0):
            raise UserError(
                "--posture-only trains the readout on a trained network: give --init RUN (and no --posture-weight)"
            )
        if not 0 <= self.average_from <= self.epochs:
            raise UserError(
                f"average_from must lie in [0, epochs = {self.epochs}] (0 = no averaging), got {self.average_from}"
            )
        if self.stature_weight is not None:
            if not 0 <= self.stature_weight <= 1:
                raise UserError(f"stature_weight must lie in [0, 1], got {self.stature_weight}")
            if self.stature_weight > 0 and (self.arch != "heatmap" or self.backend != "anny"):
                raise UserError("--stature-weight is for --arch heatmap on the Anny body model")
        if not 0 < self.lr_gamma <= 1:
            raise UserError(f"lr_gamma must lie in (0, 1], got {self.lr_gamma}")
        if not 0 <= self.val_fraction < 1:
            raise UserError(f"val_fraction must lie in [0, 1), got {self.val_fraction}")
        if self.synthesis_weight < 0 or (self.synthesis_weight > 0 and self.module != 2):
            raise UserError("synthesis_weight must be >= 0 and is a Mod2 loss (use it with --module 2)")
        if self.backend == "smpl" and not self.smpl_dir:
            raise UserError("backend smpl needs --smpl-dir (the folder holding your SMPL model file)")

    def to_json(self) -> dict:
        return {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_json(cls, record: dict) -> TrainConfig:
        fields = {f.name for f in dataclasses.fields(cls)}
        kw = {k: v for k, v in record.items() if k in fields}
        for k in ("data", "out", "mod1", "init"):
            if kw.get(k) is not None:
                kw[k] = Path(kw[k])
        return cls(**kw)

    def save(self, path: Path, net: dict) -> None:
        from pressurepose.files import atomic_write

        text = json.dumps({"train": self.to_json(), "net": net}, indent=1)
        atomic_write(Path(path), lambda tmp: Path(tmp).write_text(text))


# Fields a resumed run may change without becoming a different run.
# stature_weight says how the network is read, not how it is trained; bf16, like device, is the
# arithmetic, not the network (a run moved to a CPU without bfloat16 units goes on in float32).
RESUMABLE_CHANGES = (
    "epochs",
    "progress",
    "num_workers",
    "in_memory",
    "device",
    "bf16",
    "data",
    "out",
    "save_every",
    "stature_weight",
)

__all__ = ["PRESETS", "RESUMABLE_CHANGES", "TrainConfig"]
