"""PressureNet: the estimator (seed B.1-B.3). Pressure image -> body parameters, joints, mesh."""

from pressurepose.net.model import Estimate, NetConfig, NetInputs, PressureNet

__all__ = ["Estimate", "NetConfig", "NetInputs", "PressureNet"]
