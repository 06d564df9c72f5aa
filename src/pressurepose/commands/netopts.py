"""Inference options of a loaded network, shared by `predict`, `evaluate` and `evaluate-real`:
the heatmap arch's IK steps, its flip test (docs/network.md "Flip test, IK settings and occlusion")
and its shift test (net.shift_test)."""

from __future__ import annotations

import dataclasses

from pressurepose.errors import UserError


def with_inference_options(net, ik_steps: int | None = None, flip_test: bool = False, shift_test: bool = False):
    """`net` with its config's ik_steps, flip_test and shift_test replaced where given (UserError
    when the model is not arch heatmap or a value is out of range); unchanged when none is given."""
    changes = {}
    if ik_steps is not None:
        changes["ik_steps"] = ik_steps
    if flip_test:
        changes["flip_test"] = True
    if shift_test:
        changes["shift_test"] = True
    if not changes:
        return net
    if net.config.arch != "heatmap":
        flags = " and ".join("--" + k.replace("_", "-") for k in changes)
        verb = "apply" if len(changes) > 1 else "applies"
        raise UserError(f"{flags} {verb} to arch heatmap only; this model is arch {net.config.arch}")
    try:
        net.config = dataclasses.replace(net.config, **changes)
    except ValueError as e:
        raise UserError(str(e)) from None
    return net


def options_label(ik_steps: int | None, flip_test: bool, shift_test: bool = False) -> str:
    """' (flip test, shift test, 6 IK steps)' for a report's title; '' for the model's own settings."""
    parts = (["flip test"] if flip_test else []) + (["shift test"] if shift_test else [])
    parts += [f"{ik_steps} IK steps"] if ik_steps is not None else []
    return f" ({', '.join(parts)})" if parts else ""


def recorded_options_label(config: dict) -> str:
    """`options_label` of a report's recorded config (a report from before an option holds no key)."""
    return options_label(config.get("ik_steps"), bool(config.get("flip_test")), bool(config.get("shift_test")))


__all__ = ["options_label", "recorded_options_label", "with_inference_options"]
