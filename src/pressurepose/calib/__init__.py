"""Calibration of the mattress, mat and sensor parameters (seed A.4, A.5): docs/calibration.md."""
