"""Evaluation: error metrics (`metrics`) and reports."""
