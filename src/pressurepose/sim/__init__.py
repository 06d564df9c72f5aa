"""Physics: sim #1 settling (MuJoCo, `settle`), sim #2 pressure (`foundation`), the sensor
model and label maps (`sensor`), and the bed parameters they share (`mattress`).

MuJoCo is imported only by `settle` (and by the validation reference), so pressure images
and label maps work without it.
"""

from pressurepose.sim.mattress import GRAVITY_M_S2, MMHG_PA, MattressParams

__all__ = ["GRAVITY_M_S2", "MMHG_PA", "MattressParams"]
