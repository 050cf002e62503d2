"""bayesdrive: distributions over rule-based driver-model parameters from real trajectories."""

__version__ = "0.1.0"
