"""Training PressureNet: config and presets, data adapters, the loop, checkpoints."""

from pressurepose.train.config import TrainConfig

__all__ = ["TrainConfig"]
