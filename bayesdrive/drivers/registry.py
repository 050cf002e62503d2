"""Driver models by name, as the CLI and result metadata spell them."""

from __future__ import annotations

from types import MappingProxyType

from bayesdrive.drivers.base import DriverModel
from bayesdrive.drivers.cidm import CIDM
from bayesdrive.drivers.gipps import GIPPS
from bayesdrive.drivers.idm import IDM
from bayesdrive.drivers.measurement_noise import with_measurement_noise

__all__ = ["MODELS", "get_model"]

# The measurement-noise variant is the latent-state engine's (pmmh) model of noisy positions.
MODELS = MappingProxyType(
    {model.name: model for model in (IDM, CIDM, GIPPS, with_measurement_noise(IDM))}
)


def get_model(name: str) -> DriverModel:
    """The driver model called ``name`` ("idm", "cidm", "gipps"); a KeyError lists the known names."""
    try:
        return MODELS[name]
    except KeyError:
        raise KeyError(f"unknown driver model {name!r}; known models: {sorted(MODELS)}") from None
