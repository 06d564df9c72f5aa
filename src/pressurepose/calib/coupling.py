"""Sim #1 against sim #2 on the calibration objects (seed eq. 17's role)."""

from __future__ import annotations

from pressurepose.calib.loss import CalibrationLoss
from pressurepose.calib.objects import CalibObject, SceneSimulator
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.objects import settle_capsule


def coupling_check(loss: CalibrationLoss, params: MattressParams) -> list[dict]:
    """Sim #1 (MuJoCo, the foundation law applied to capsules) against sim #2 for every
    object: each capsule is settled alone at the bed's centre, along the bed (seed eq. 17's
    role: both simulations must sink an object alike)."""
    mat = loss.mat
    rows = []
    for o in loss.sim.objects:
        centred = CalibObject(o.length_m, o.radius_m, o.mass_kg, 0.9, mat.sensing_width_m / 2, 0.0, o.name)
        q2 = float(SceneSimulator([[centred]], mat, loss.sub)(params).compression_m[0])
        s1 = settle_capsule(
            o.length_m, o.radius_m, o.mass_kg, xy=(0.9, mat.sensing_width_m / 2), params=params, mat=mat
        )
        rows.append(
            {
                "name": o.name,
                "sim2_sink_m": round(q2, 6),
                "sim1_sink_m": round(s1["sink_m"], 6),
                "sim1_settled": s1["settled"],
                "relative_difference": round((s1["sink_m"] - q2) / q2, 4),
            }
        )
    return rows


__all__ = ["coupling_check"]
