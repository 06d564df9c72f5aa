"""pressurepose: see a person in bed through a pressure mat (Bodies at Rest, open and tested)."""

__version__ = "0.1.0"
