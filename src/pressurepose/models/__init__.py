"""The default PressureNet shipped with the package (docs/model-card.md).

`--model default` (the default of `predict`, `evaluate`, `evaluate-real` and `demo`) names the
run folder `pressurepose/models/default/`: model.safetensors (weights and the training config
as metadata, no pickles) and its evaluation report. A folder called "default" in the working
directory wins over the packaged one, as any existing path does.
"""

from __future__ import annotations

from pathlib import Path

from pressurepose.errors import UserError

DEFAULT = "default"
"""The model name that resolves to the packaged network."""

_HERE = Path(__file__).resolve().parent


def default_model_dir() -> Path:
    """The packaged default model's run folder (it holds model.safetensors)."""
    return _HERE / "default"


def resolve_model(path: str | Path) -> Path:
    """A run folder: `path` itself when it exists, the packaged model for "default"."""
    path = Path(path)
    if not path.exists() and str(path) == DEFAULT:
        folder = default_model_dir()
        if not (folder / "model.safetensors").is_file():
            raise UserError(
                "no default model in this installation (pressurepose/models/default/"
                "model.safetensors missing); reinstall pressurepose or pass --model RUN"
            )
        return folder
    return path


__all__ = ["DEFAULT", "default_model_dir", "resolve_model"]
