"""Body models behind one interface (Anny by default, SMPL optional), J24, joint limits."""

from __future__ import annotations

import torch

from pressurepose.body.joints import J24_NAMES, J24_PARENTS, NUM_JOINTS, NUM_POSE_JOINTS
from pressurepose.body.model import BodyMeasurements, BodyModel
from pressurepose.body.params import BodyOutput, BodyParams
from pressurepose.errors import UserError

BACKENDS = ("anny", "smpl")


def load_body_model(
    backend: str = "anny",
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
    **options,
) -> BodyModel:
    """A body model by backend name: "anny" (default, embedded) or "smpl" (user's files;
    options `model_dir`, `gender`)."""
    return backend_class(backend)(dtype=dtype, device=device, **options)


def backend_class(backend: str) -> type[BodyModel]:
    """The BodyModel class of a backend name (its class-level facts, e.g. `shape_bounds`,
    without loading the model): the one place a backend's name selects code."""
    if backend == "anny":
        from pressurepose.body.anny_backend import AnnyBody

        return AnnyBody
    if backend == "smpl":
        from pressurepose.body.smpl_backend import SmplBody

        return SmplBody
    raise UserError(f"unknown body backend {backend!r}; expected one of {', '.join(BACKENDS)}")


__all__ = [
    "BACKENDS",
    "BodyMeasurements",
    "BodyModel",
    "BodyOutput",
    "BodyParams",
    "J24_NAMES",
    "J24_PARENTS",
    "NUM_JOINTS",
    "NUM_POSE_JOINTS",
    "backend_class",
    "load_body_model",
]
