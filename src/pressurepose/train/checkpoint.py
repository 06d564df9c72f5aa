"""Checkpoints as safetensors (tensors only, never pickles) with the configs as metadata.

RUN/model.safetensors: the network's CNN weights ("model/..."), metadata {"config": the
config.json text}. RUN/checkpoint.safetensors: the same plus Adam's moments and steps
("optim/<i>/<name>"), the epoch reached and, once `--average-from` begins, the weight average
("average/...", "average_count"), for resuming. `load_network(RUN)` needs nothing
but the run folder: the architecture comes from the metadata, never from flags.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import torch

from pressurepose.errors import UserError
from pressurepose.files import atomic_write
from pressurepose.net.model import NetConfig, PressureNet
from pressurepose.train.average import COUNT as AVERAGE_COUNT
from pressurepose.train.average import PREFIX as AVERAGE_PREFIX
from pressurepose.train.average import WeightAverage
from pressurepose.validate import check_tensor_shapes, field

MODEL_FILE = "model.safetensors"
CHECKPOINT_FILE = "checkpoint.safetensors"
FORMAT = "pressurepose-net"


def _save(path: Path, tensors: dict[str, torch.Tensor], metadata: dict[str, str]) -> Path:
    from safetensors.torch import save_file

    tensors = {k: v.detach().contiguous().cpu() for k, v in tensors.items()}
    return atomic_write(Path(path), lambda tmp: save_file(tensors, str(tmp), metadata=metadata))


def _load(path: Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    from safetensors import SafetensorError, safe_open

    path = Path(path)
    if not path.is_file():
        raise UserError(f"no {path.name} in {path.parent}; is it a `pressurepose train` run folder?")
    try:
        with safe_open(str(path), framework="pt") as f:
            return {k: f.get_tensor(k) for k in f.keys()}, dict(f.metadata() or {})
    except (SafetensorError, OSError) as exc:
        raise UserError(f"{path} is not a readable safetensors checkpoint ({exc})") from None


def save_model(run: Path, net: PressureNet, config_record: dict, state: dict[str, torch.Tensor] | None = None) -> Path:
    """RUN/model.safetensors: the network's trainable state (or `state`, e.g. a weight average)."""
    state = net.trainable_state() if state is None else state
    tensors = {f"model/{k}": v for k, v in state.items()}
    Path(run).mkdir(parents=True, exist_ok=True)
    return _save(Path(run) / MODEL_FILE, tensors, {"format": FORMAT, "config": json.dumps(config_record)})


def save_checkpoint(
    run: Path,
    net: PressureNet,
    optimizer: torch.optim.Optimizer,
    epoch: int,
    config_record: dict,
    average: WeightAverage | None = None,
) -> Path:
    tensors = {f"model/{k}": v for k, v in net.trainable_state().items()}
    for i, state in optimizer.state_dict()["state"].items():
        for name, value in state.items():
            tensors[f"optim/{i}/{name}"] = torch.as_tensor(value)
    if average is not None and average.count:
        tensors.update(average.tensors())
    meta = {"format": FORMAT, "config": json.dumps(config_record), "epoch": str(epoch)}
    return _save(Path(run) / CHECKPOINT_FILE, tensors, meta)


def load_checkpoint(
    run: Path, net: PressureNet, optimizer: torch.optim.Optimizer, average: WeightAverage | None = None
) -> tuple[int, dict]:
    """Restore weights, optimizer state and the weight average if one was saved; returns (epochs
    done, config record). Every tensor is checked against the network and optimizer first
    (UserError naming the file)."""
    path = Path(run) / CHECKPOINT_FILE
    tensors, meta = _load(path)
    record = _config_record(meta, path)
    epoch = meta.get("epoch", "")
    if not (epoch.isascii() and epoch.isdigit()):
        raise UserError(f"{path}: metadata field 'epoch' must be a whole number, got {epoch[:40]!r}")
    weights = _strip(tensors, "model/")
    check_tensor_shapes(weights, {k: v.shape for k, v in net.trainable_state().items()}, path)
    params = [p for group in optimizer.param_groups for p in group["params"]]
    state: dict[int, dict] = {}
    for key, value in tensors.items():
        if key.startswith("optim/"):
            parts = key.split("/", 2)
            if (
                len(parts) != 3
                or not parts[1].isdigit()
                or int(parts[1]) >= len(params)
                or parts[2] not in ("step", "exp_avg", "exp_avg_sq")
            ):
                raise UserError(f"{path}: tensor {key!r} is not Adam state of this network's parameters")
            i, name = int(parts[1]), parts[2]
            want = () if name == "step" else tuple(params[i].shape)
            if tuple(value.shape) != want:
                raise UserError(f"{path}: tensor {key!r} has shape {tuple(value.shape)}, expected {want}")
            state.setdefault(i, {})[name] = value
    averaged = _strip(tensors, AVERAGE_PREFIX)
    if averaged:
        check_tensor_shapes(averaged, {k: v.shape for k, v in net.trainable_state().items()}, path)
        count = tensors.get(AVERAGE_COUNT)
        if count is None or count.shape != () or count.is_floating_point() or int(count) < 1:
            raise UserError(f"{path}: the weight average lacks a whole, positive tensor {AVERAGE_COUNT!r}")
        if average is not None:
            average.load(tensors)
    net.load_trainable_state(weights)
    groups = optimizer.state_dict()["param_groups"]
    optimizer.load_state_dict({"state": state, "param_groups": groups})
    return int(epoch), record


def _strip(tensors: dict[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    return {k[len(prefix) :]: v for k, v in tensors.items() if k.startswith(prefix)}


def _config_record(meta: dict[str, str], path: Path) -> dict:
    """The config record in a network file's metadata, checked: JSON, an object with "net"."""
    if meta.get("format") != FORMAT or "config" not in meta:
        raise UserError(f"{path} is not a pressurepose network file (metadata 'format' and 'config')")
    try:
        record = json.loads(meta["config"])
    except (json.JSONDecodeError, RecursionError) as exc:
        raise UserError(f"{path}: metadata field 'config' is not readable JSON ({exc})") from None
    field(record, "net", "dict", path, "config.")
    return record


def read_model(run: Path) -> tuple[dict[str, torch.Tensor], dict]:
    """(weights, config record) of a run's model.safetensors; run "default" is the packaged model."""
    from pressurepose.models import resolve_model

    run = resolve_model(run)
    path = run / MODEL_FILE
    tensors, meta = _load(path)
    return _strip(tensors, "model/"), _config_record(meta, path)


# NetConfig fields as a network file records them, with their kinds (validate.KINDS).
NET_FIELDS = {
    "arch": "str",
    "backend": "str",
    "modules": "int",
    "gender_input": "bool",
    "height_weight": "bool",
    "dropout": "number",
    "width": "int",
    "ik_steps": "int",
    "flip_test": "bool",
    "shift_test": "bool",
    "posture_consistent": "bool",
    "posture_head": "bool",
    "antialias": "bool",
    "texture_sigma_taxels": "number",
    "stature_weight": "number",
    "stature_head": "bool",
}
MAX_WIDTH = 16


def net_config_from_record(record: dict, path: str | Path = "the run's metadata") -> NetConfig:
    """The NetConfig a config record describes, every field checked (UserError naming `path`)."""
    net = field(record, "net", "dict", path, "config.")
    unknown = sorted(set(net) - {f.name for f in dataclasses.fields(NetConfig)})
    if unknown:
        raise UserError(f"{path}: unknown fields config.net.{', config.net.'.join(unknown)}")
    for key, kind in NET_FIELDS.items():
        if key in net:
            field(net, key, kind, path, "config.net.")
    if not 1 <= net.get("width", 1) <= MAX_WIDTH:
        raise UserError(f"{path}: field 'config.net.width' must lie in [1, {MAX_WIDTH}], got {net['width']}")
    if net.get("smpl_dir") is not None:
        field(net, "smpl_dir", "str", path, "config.net.")
    for key, allowed in (("arch", ("paper", "fast", "heatmap")), ("backend", ("anny", "smpl")), ("modules", (1, 2))):
        if key in net and net[key] not in allowed:
            raise UserError(f"{path}: field 'config.net.{key}' must be one of {allowed}, got {net[key]!r}")
    try:
        return NetConfig(**net)
    except ValueError as exc:
        raise UserError(f"{path}: {exc}") from None


def load_network(run: Path, device: str | torch.device = "cpu", body=None) -> tuple[PressureNet, dict]:
    """The trained network of a run folder, in eval mode, and its config record; the file's
    tensors must be the network its metadata describes, name by name and shape by shape."""
    from pressurepose.models import resolve_model

    path = resolve_model(run) / MODEL_FILE
    weights, record = read_model(run)
    net = PressureNet(net_config_from_record(record, path), body=body)
    check_tensor_shapes(weights, {k: v.shape for k, v in net.trainable_state().items()}, path)
    net.load_trainable_state(weights)
    return net.to(device).eval(), record


__all__ = [
    "CHECKPOINT_FILE",
    "MODEL_FILE",
    "load_checkpoint",
    "load_network",
    "read_model",
    "save_checkpoint",
    "save_model",
]
