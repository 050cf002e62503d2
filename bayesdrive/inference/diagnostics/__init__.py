"""Checks of the engines: agreement between engines, convergence, simulation-based calibration and
the synthetic followers they are run on."""
