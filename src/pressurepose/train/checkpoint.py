"""Checkpoints as safetensors (tensors only, never pickles) with the configs as metadata.

RUN/model.safetensors: the network's CNN weights ("model/..."), metadata {"config": the
config.json text}. RUN/checkpoint.safetensors: the same plus Adam's moments and steps
("optim/<i>/<name>") and the epoch reached, for resuming. `load_network(RUN)` needs nothing
but the run folder: the architecture comes from the metadata, never from flags.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from pressurepose.errors import UserError
from pressurepose.files import atomic_write
from pressurepose.net.model import NetConfig, PressureNet

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


def save_model(run: Path, net: PressureNet, config_record: dict) -> Path:
    tensors = {f"model/{k}": v for k, v in net.trainable_state().items()}
    return _save(Path(run) / MODEL_FILE, tensors, {"format": FORMAT, "config": json.dumps(config_record)})


def save_checkpoint(run: Path, net: PressureNet, optimizer: torch.optim.Optimizer, epoch: int,
                    config_record: dict) -> Path:
    tensors = {f"model/{k}": v for k, v in net.trainable_state().items()}
    for i, state in optimizer.state_dict()["state"].items():
        for name, value in state.items():
            tensors[f"optim/{i}/{name}"] = torch.as_tensor(value)
    meta = {"format": FORMAT, "config": json.dumps(config_record), "epoch": str(epoch)}
    return _save(Path(run) / CHECKPOINT_FILE, tensors, meta)


def load_checkpoint(run: Path, net: PressureNet, optimizer: torch.optim.Optimizer) -> tuple[int, dict]:
    """Restore weights and optimizer state; returns (epochs done, config record)."""
    tensors, meta = _load(Path(run) / CHECKPOINT_FILE)
    net.load_trainable_state(_strip(tensors, "model/"))
    state: dict[int, dict] = {}
    for key, value in tensors.items():
        if key.startswith("optim/"):
            _, i, name = key.split("/", 2)
            state.setdefault(int(i), {})[name] = value
    groups = optimizer.state_dict()["param_groups"]
    optimizer.load_state_dict({"state": state, "param_groups": groups})
    return int(meta["epoch"]), json.loads(meta["config"])


def _strip(tensors: dict[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    return {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}


def read_model(run: Path) -> tuple[dict[str, torch.Tensor], dict]:
    """(weights, config record) of a run's model.safetensors; run "default" is the packaged model."""
    from pressurepose.models import resolve_model

    run = resolve_model(run)
    tensors, meta = _load(run / MODEL_FILE)
    if meta.get("format") != FORMAT or "config" not in meta:
        raise UserError(f"{run / MODEL_FILE} is not a pressurepose network file")
    return _strip(tensors, "model/"), json.loads(meta["config"])


def net_config_from_record(record: dict) -> NetConfig:
    try:
        return NetConfig(**record["net"])
    except (KeyError, TypeError) as exc:
        raise UserError(f"network config missing or unreadable in the run's metadata ({exc})") from None


def load_network(run: Path, device: str | torch.device = "cpu", body=None) -> tuple[PressureNet, dict]:
    """The trained network of a run folder, in eval mode, and its config record."""
    weights, record = read_model(run)
    net = PressureNet(net_config_from_record(record), body=body)
    net.load_trainable_state(weights)
    return net.to(device).eval(), record


__all__ = ["CHECKPOINT_FILE", "MODEL_FILE", "load_checkpoint", "load_network", "read_model", "save_checkpoint",
           "save_model"]
