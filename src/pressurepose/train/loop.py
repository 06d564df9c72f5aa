"""The training loop, top to bottom: data -> network -> loss -> Adam, one checkpoint per epoch.

Every epoch e draws its order, augmentation and dropout from generators seeded by
(seed, e), so a run resumed from its checkpoint after epoch e equals one never interrupted.
Writes RUN/config.json first, then after every epoch checkpoint.safetensors, model.safetensors
(the weight average from --average-from on, the last epoch's weights then in last/),
metrics.jsonl + metrics.csv (one row per epoch) - all atomically (`pressurepose train` adds
metrics.png: `commands.train`).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from pressurepose.errors import UserError
from pressurepose.net.heatmap import localisation_loss
from pressurepose.net.losses import Targets, joint_error_m, module_loss
from pressurepose.net.model import NetConfig, NetInputs, PressureNet
from pressurepose.net.posture import posture_loss
from pressurepose.train.augment import augment_batch
from pressurepose.train.average import WeightAverage
from pressurepose.train.checkpoint import (
    CHECKPOINT_FILE,
    MODEL_FILE,
    load_checkpoint,
    net_config_from_record,
    read_model,
    save_checkpoint,
    save_model,
)
from pressurepose.train.config import RESUMABLE_CHANGES, TrainConfig
from pressurepose.train.data import collate, in_memory, open_dataset
from pressurepose.train.metrics import read_metrics, write_metrics
from pressurepose.train.precision import train_in_bf16
from pressurepose.validate import check_tensor_shapes, field, read_json_object

log = logging.getLogger(__name__)


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise UserError("device cuda asked for, but torch sees no CUDA device; use --device cpu")
    return torch.device(name)


def batch_inputs(batch: dict[str, torch.Tensor], device: torch.device) -> tuple[NetInputs, Targets]:
    b = {k: v.to(device, non_blocking=True) for k, v in batch.items()}
    inputs = NetInputs(
        pressure_mmhg=b["pressure_mmhg"], gender=b["gender"], height_m=b["height_m"], mass_kg=b["mass_kg"]
    )
    return inputs, Targets(joints=b["joints"], shape=b["shape"], depth_mm=b["depth_mm"], contact=b["contact"])


def step_loss(
    net: PressureNet,
    inputs: NetInputs,
    targets: Targets,
    cfg: TrainConfig,
    augment: bool,
    generator: torch.Generator | None,
) -> tuple[torch.Tensor, dict[str, float], torch.Tensor]:
    """Loss of the module being trained, its parts, and the (B,) joint error of its estimate."""
    if augment:
        inputs, targets = augment_batch(inputs, targets, cfg, generator)
    ests = net(inputs, augment=augment, generator=generator, mesh=cfg.module == 2)
    est = ests[-1]
    scale = net.head.shape_scale()
    if cfg.module == 1:
        loss, parts = module_loss(est.joints, est.params.shape, targets, scale)
        if est.localisation is not None:
            located, located_parts = localisation_loss(est.localisation, targets.joints, net.mat)
            loss, parts = loss + located, {**parts, **located_parts}
        if est.localisation is not None and est.localisation.posture_logits is not None:
            posture, posture_parts = posture_loss(est.localisation.posture_logits, targets.joints)
            loss = posture if cfg.posture_only else loss + cfg.posture_weight * posture
            parts = {**parts, **posture_parts}
    else:
        loss, parts = module_loss(est.joints, est.params.shape, targets, scale, est.depth_mm, est.contact)
        if cfg.synthesis_weight > 0:
            from pressurepose.net.synthesis import synthesis_loss

            syn = synthesis_loss(net, est, inputs.pressure_mmhg)
            parts["synthesis"] = float(syn.detach())
            loss = loss + cfg.synthesis_weight * syn
    return loss, parts, joint_error_m(est.joints.detach(), targets.joints)


def build_network(cfg: TrainConfig, device: torch.device) -> PressureNet:
    init_weights, init_record, init_cfg = _read_init(cfg.init) if cfg.init is not None else (None, None, None)
    # the low-pass before subsampling has no weights: a fine-tune keeps the other network's, and
    # --antialias switches it on for one that lacks it
    inherited = init_cfg is not None and init_cfg.antialias and cfg.arch == "heatmap"
    netcfg = NetConfig(
        arch=cfg.arch,
        backend=cfg.backend,
        modules=cfg.module,
        gender_input=cfg.gender_input,
        height_weight=cfg.height_weight,
        smpl_dir=cfg.smpl_dir,
        dropout=cfg.dropout,
        width=cfg.width,
        texture_sigma_taxels=cfg.texture_sigma,
        posture_head=cfg.posture_weight > 0 or cfg.posture_only,
        antialias=cfg.antialias or inherited,
    )
    if cfg.module == 2:
        weights, record = read_model(cfg.mod1)
        m1 = net_config_from_record(record, Path(cfg.mod1) / MODEL_FILE)
        if m1.modules != 1:
            raise UserError(f"{cfg.mod1} is not a Mod1 run (it holds {m1.modules} modules)")
        mismatch = [
            f
            for f in ("arch", "backend", "gender_input", "height_weight", "width")
            if getattr(m1, f) != getattr(netcfg, f)
        ]
        if mismatch:
            raise UserError(f"Mod1 run {cfg.mod1} differs in {mismatch}; train Mod2 with the same settings")
    body = netcfg.load_body(device=device)
    torch.manual_seed(cfg.seed)  # the initial weights
    net = PressureNet(netcfg, body=body)
    if cfg.module == 2:
        mod1 = {k[len("mod1.") :]: v for k, v in weights.items() if k.startswith("mod1.")}
        check_tensor_shapes(mod1, {k: v.shape for k, v in net.mod1.state_dict().items()}, Path(cfg.mod1) / MODEL_FILE)
        net.mod1.load_state_dict(mod1)
        net.freeze_mod1()
    if init_cfg is not None:
        _load_init(net, cfg.init, init_weights, init_record, init_cfg)
    if cfg.stature_weight is not None:  # how the network is read, given: over the other network's
        net.config = dataclasses.replace(net.config, stature_weight=cfg.stature_weight)
    if cfg.posture_only:
        net.freeze_all_but_readout()
    return net.to(device)


# NetConfig fields that say how a trained network is read, not what it is (eval only).
INFERENCE_FIELDS = ("ik_steps", "flip_test", "shift_test", "stature_weight", "stature_head", "posture_consistent")


def _read_init(init: Path) -> tuple[dict, dict, NetConfig]:
    """The weights, config record and NetConfig of the network a fine-tune starts from."""
    weights, record = read_model(init)
    return weights, record, net_config_from_record(record, Path(init) / MODEL_FILE)


def _load_init(net: PressureNet, init: Path, weights: dict, record: dict, other: NetConfig) -> None:
    """Start from the weights of another run's network `other` (fine-tuning, read by `_read_init`),
    which must be the same network: same arch, width, modules, inputs, input smoothing and body
    model. A posture readout the other network lacks starts from fresh weights; one it has that
    this one lacks is left out. Its inference settings (INFERENCE_FIELDS) are kept: a fine-tune
    of the packaged model reads its images as that model does."""
    own = net.trainable_state()
    readout = {k for k in own if k.startswith("mod1.posture.")}
    weights = {k: v for k, v in weights.items() if k in readout or not k.startswith("mod1.posture.")}
    weights.update({k: own[k] for k in readout if k not in weights})  # a readout the other lacks starts fresh
    fields = ("arch", "width", "modules", "backend", "gender_input", "height_weight", "texture_sigma_taxels")
    mismatch = [f for f in fields if getattr(other, f) != getattr(net.config, f)]
    if mismatch:
        raise UserError(
            f"--init {init} is a different network ({', '.join(mismatch)} differ); "
            "train with the same settings or drop --init"
        )
    check_tensor_shapes(weights, {k: v.shape for k, v in net.trainable_state().items()}, Path(init) / MODEL_FILE)
    net.load_trainable_state(weights)
    # How the other network is read - inference-only settings chosen for its weights (IK steps,
    # flip test, the height's blend with the localised skeleton) - carries over to the fine-tune.
    carried = {f: getattr(other, f) for f in INFERENCE_FIELDS}
    if not net.config.posture_head:
        carried["posture_consistent"] = False
    net.config = dataclasses.replace(net.config, **carried)


def _split(n: int, cfg: TrainConfig) -> tuple[list[int], list[int]]:
    order = np.random.default_rng(cfg.seed).permutation(n)
    n_val = int(round(cfg.val_fraction * n)) if n >= 20 else 0
    return sorted(order[n_val:].tolist()), sorted(order[:n_val].tolist())


def _check_resume(run: Path, cfg: TrainConfig) -> TrainConfig:
    """The config to resume `run` with (UserError when it is another run's); a stature weight not
    given now is the run's own."""
    path = run / "config.json"
    if not path.is_file():
        return cfg
    hint = "; resume with an intact run folder or train into a new --out folder"
    saved = field(read_json_object(path, "run config", hint), "train", "dict", path, hint=hint)
    now = cfg.to_json()
    # A field added after the run was saved counts at its default (older runs resume).
    defaults = {f.name: f.default for f in dataclasses.fields(TrainConfig)}
    differ = [k for k in now if k not in RESUMABLE_CHANGES and saved.get(k, defaults.get(k)) != now[k]]
    if differ:
        raise UserError(
            f"{run} holds a run with different settings ({', '.join(differ)}); "
            "resume with the same settings or train into a new --out folder"
        )
    if cfg.stature_weight is None and saved.get("stature_weight") is not None:
        cfg = dataclasses.replace(cfg, stature_weight=saved["stature_weight"])
    return cfg


def train(
    cfg: TrainConfig,
    dataset: torch.utils.data.Dataset | None = None,
    on_save: Callable[[Path, list[dict]], None] | None = None,
) -> Path:
    """Train as configured; returns the run folder. `dataset` replaces `cfg.data` (tests);
    `on_save(run, metrics rows)` runs after every save (the command draws metrics.png)."""
    cfg = cfg.resolved()
    run = Path(cfg.out)
    if dataset is None:
        if cfg.data is None:
            raise UserError("no training data: give --data DIR")
        dataset = open_dataset(cfg.data)
    if len(dataset) == 0:
        raise UserError("the training dataset is empty")
    device = pick_device(cfg.device)
    run.mkdir(parents=True, exist_ok=True)
    resuming = (run / CHECKPOINT_FILE).is_file()
    if resuming:
        cfg = _check_resume(run, cfg)
    if cfg.in_memory:
        dataset = in_memory(dataset)
    net = build_network(cfg, device)
    if cfg.bf16:
        train_in_bf16(net, device)
    record = {"train": cfg.to_json(), "net": {**net.config.__dict__}}
    cfg.save(run / "config.json", record["net"])
    params = [p for p in net.parameters() if p.requires_grad]
    opt = torch.optim.Adam(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
    average = WeightAverage(net) if cfg.average_from else None
    start = 0
    if resuming:
        start, _ = load_checkpoint(run, net, opt, average)
        log.info("resuming %s after epoch %d", run, start)
        expected = max(0, start - cfg.average_from + 1) if average is not None else 0
        if average is not None and average.count != expected:
            raise UserError(
                f"{run / CHECKPOINT_FILE} holds a weight average of {average.count} epochs where "
                f"--average-from {cfg.average_from} after epoch {start} needs {expected}; train into a new --out folder"
            )
    history = [r for r in read_metrics(run) if r["epoch"] <= start] if resuming else []
    train_idx, val_idx = _split(len(dataset), cfg)
    for epoch in range(start + 1, cfg.epochs + 1):
        for group in opt.param_groups:  # a function of the epoch alone, so resuming keeps it
            group["lr"] = cfg.lr * cfg.lr_gamma ** (epoch - 1)
        row = _epoch(net, opt, dataset, train_idx, val_idx, cfg, epoch, device)
        if average is not None and epoch >= cfg.average_from:
            average.update()
            if val_idx:
                with average.swapped_in(net):
                    scores = evaluate(net, torch.utils.data.Subset(dataset, val_idx), cfg, device)
                row.update({f"average_{k}": v for k, v in scores.items()})
        history.append(row)
        if epoch % cfg.save_every == 0 or epoch == cfg.epochs:
            save_checkpoint(run, net, opt, epoch, record, average)
            _save_models(run, net, record, average)
            write_metrics(run, history)
            if on_save is not None:
                on_save(run, history)
        log.info(
            "epoch %d/%d: loss %.4f, train MPJPE %.1f mm%s, %.0f img/s",
            epoch,
            cfg.epochs,
            row["loss"],
            row["train_mpjpe_mm"],
            f", val MPJPE {row['val_mpjpe_mm']:.1f} mm" if "val_mpjpe_mm" in row else "",
            row["images_per_s"],
        )
    if start >= cfg.epochs:
        _save_models(run, net, record, average)
    return run


def _save_models(run: Path, net: PressureNet, record: dict, average: WeightAverage | None) -> None:
    """model.safetensors: the weight average once it has begun (the last epoch's weights in
    last/model.safetensors), else the network's own weights."""
    if average is None or not average.count:
        save_model(run, net, record)
        return
    save_model(run / "last", net, record)
    save_model(run, net, record, average.state())


def _epoch(net, opt, dataset, train_idx, val_idx, cfg, epoch, device) -> dict:
    torch.manual_seed(cfg.seed * 100003 + epoch)  # dropout of this epoch
    gen = torch.Generator().manual_seed(cfg.seed * 100003 + epoch)
    order = [train_idx[i] for i in torch.randperm(len(train_idx), generator=gen).tolist()]
    loader = torch.utils.data.DataLoader(
        dataset, batch_size=cfg.batch_size, sampler=order, collate_fn=collate, num_workers=cfg.num_workers
    )
    net.train()  # with --posture-only the frozen network keeps its batch statistics, drops no units
    totals: dict[str, float] = {}
    n_seen, err_sum, t0 = 0, 0.0, time.perf_counter()
    with _progress(cfg.progress, f"epoch {epoch}/{cfg.epochs}", len(loader)) as advance:
        for batch in loader:
            inputs, targets = batch_inputs(batch, device)
            loss, parts, err = step_loss(net, inputs, targets, cfg, cfg.augment, gen)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            B = inputs.batch_size
            n_seen += B
            err_sum += float(err.sum())
            for k, v in {"loss": float(loss.detach()), **parts}.items():
                totals[k] = totals.get(k, 0.0) + v * B
            advance(f"loss {float(loss.detach()):.3f}")
    seconds = time.perf_counter() - t0
    row = {
        "epoch": epoch,
        **{k: v / n_seen for k, v in totals.items()},
        "train_mpjpe_mm": 1000 * err_sum / n_seen,
        "images_per_s": n_seen / seconds,
        "seconds": seconds,
        "lr": opt.param_groups[0]["lr"],
    }
    if val_idx:
        row.update(evaluate(net, torch.utils.data.Subset(dataset, val_idx), cfg, device))
    return row


@torch.no_grad()
def evaluate(net: PressureNet, dataset, cfg: TrainConfig, device: torch.device) -> dict[str, float]:
    """Validation loss and MPJPE (mm) of the trained module (and the share of postures read
    right, with a posture readout), no augmentation."""
    net.eval()
    loader = torch.utils.data.DataLoader(dataset, batch_size=cfg.batch_size, collate_fn=collate)
    loss_sum, err_sum, right, n = 0.0, 0.0, 0.0, 0
    for batch in loader:
        inputs, targets = batch_inputs(batch, device)
        loss, parts, err = step_loss(net, inputs, targets, cfg, False, None)
        loss_sum += float(loss) * inputs.batch_size
        err_sum += float(err.sum())
        right += parts.get("posture_accuracy", 0.0) * inputs.batch_size
        n += inputs.batch_size
    scores = {"val_loss": loss_sum / n, "val_mpjpe_mm": 1000 * err_sum / n}
    if net.config.posture_head:
        scores["val_posture_accuracy"] = right / n
    return scores


class _progress:
    """A rich progress bar (or nothing); the context value advances it by one batch."""

    def __init__(self, enabled: bool, what: str, total: int) -> None:
        self.enabled, self.what, self.total = enabled, what, total

    def __enter__(self):
        if not self.enabled:
            return lambda note="": None
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        self.bar = Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeRemainingColumn(),
            TextColumn("{task.fields[note]}"),
            transient=True,
        )
        self.bar.__enter__()
        task = self.bar.add_task(self.what, total=self.total, note="")
        return lambda note="": self.bar.update(task, advance=1, note=note)

    def __exit__(self, *exc):
        if self.enabled:
            self.bar.__exit__(*exc)
        return False


__all__ = ["evaluate", "pick_device", "read_metrics", "train"]
