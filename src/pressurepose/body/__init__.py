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
    if backend == "anny":
        from pressurepose.body.anny_backend import AnnyBody

        return AnnyBody(dtype=dtype, device=device, **options)
    if backend == "smpl":
        from pressurepose.body.smpl_backend import SmplBody

        return SmplBody(dtype=dtype, device=device, **options)
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
    "load_body_model",
]
