"""Physical constants and unit conversions shared across the pipeline (SI inside; mmHg at
the sensor boundary, docs/conventions.md)."""

GRAVITY_M_S2 = 9.81
MMHG_PA = 133.322  # pascals per mmHg

__all__ = ["GRAVITY_M_S2", "MMHG_PA"]
