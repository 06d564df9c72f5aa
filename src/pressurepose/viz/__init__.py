"""Figures: pressure images, bodies on the mat (matplotlib PNGs)."""
