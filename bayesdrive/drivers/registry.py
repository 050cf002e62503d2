"""Driver models by name, as the CLI and result metadata spell them.

A name is a base model (``idm``, ``cidm``) optionally joined by ``+`` to one extension named by the
cause it answers (``idm+reaction_delay``, ``idm+autocorrelated_noise``; the causes of
:data:`~bayesdrive.drivers.extensions.CAUSES`). The parts may come in any order; a model's
canonical name puts the base first, so a result written under one spelling is recognised under
another. ``idm+obs_noise`` is the latent-state engine's (pmmh) model of noisy positions without
exact speeds (:mod:`bayesdrive.drivers.measurement_noise`).
"""

from __future__ import annotations

from types import MappingProxyType

from bayesdrive.drivers.base import DriverModel
from bayesdrive.drivers.cidm import CIDM
from bayesdrive.drivers.extensions import CAUSES, extend
from bayesdrive.drivers.idm import IDM
from bayesdrive.drivers.measurement_noise import with_measurement_noise

__all__ = ["BASES", "MODELS", "canonical_name", "get_model"]

BASES = MappingProxyType({model.name: model for model in (IDM, CIDM)})
# Models that are not a base plus an extension.
MODELS = MappingProxyType({**BASES, "idm+obs_noise": with_measurement_noise(IDM)})


def canonical_name(name: str) -> str:
    """``name`` with its base model first ("reaction_delay+idm" -> "idm+reaction_delay");
    a KeyError names the unknown or missing part."""
    if name in MODELS:
        return name
    parts = [part.strip() for part in name.split("+")]
    bases = [part for part in parts if part in BASES]
    unknown = [part for part in parts if part not in BASES and part not in CAUSES]
    if unknown or len(bases) != 1:
        raise KeyError(
            f"unknown driver model {name!r}: "
            + (f"unknown part(s) {unknown}; " if unknown else "")
            + f"a name is one base model of {sorted(BASES)} joined by '+' to at most one "
            f"extension of {list(CAUSES)}, or one of {sorted(MODELS)}"
        )
    causes = [part for part in parts if part in CAUSES]
    if len(causes) > 1:
        raise KeyError(
            f"driver model {name!r} joins {len(causes)} extensions; composing extensions is not "
            "supported yet (one extension per model)"
        )
    return "+".join(bases + causes)


def get_model(name: str) -> DriverModel:
    """The driver model called ``name`` (module docstring); a KeyError says what is unknown."""
    canonical = canonical_name(name)
    if canonical in MODELS:
        return MODELS[canonical]
    base, cause = canonical.split("+")
    return extend(cause, BASES[base]).model
