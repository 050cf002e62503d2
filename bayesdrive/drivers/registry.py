"""Driver models by name, as the CLI and result metadata spell them.

A name is a base model (``idm``, ``cidm``, ``gipps``, ``ovm``) optionally joined by ``+`` to extensions
named by the causes they answer (``idm+reaction_delay``,
``idm+reaction_delay+autocorrelated_noise``; the causes of
:data:`~bayesdrive.drivers.extensions.CAUSES`, composed by the rules of
:mod:`bayesdrive.drivers.extensions`). The parts may come in any order; a model's canonical name
puts the base first and the extensions in the order they are applied, so a result written under
one spelling is recognised under another. ``idm+measurement_noise`` is the one measurement-noise model
(:mod:`bayesdrive.drivers.measurement_noise`), for speeds recorded exactly and for the latent-state
engine alike; results saved under its former name ``idm+obs_noise`` are refused with a message.
``+video_noise`` (:mod:`bayesdrive.drivers.video_noise`) is the other observation model, for
positions whose speeds were differenced from them: an extension of the same kind, so a model has
one observation model or none.
"""

from __future__ import annotations

from types import MappingProxyType

from bayesdrive.drivers.base import DriverModel
from bayesdrive.drivers.cidm import CIDM
from bayesdrive.drivers.extensions import PARTS, compose, composition_problem, ordered_causes
from bayesdrive.drivers.gipps import GIPPS
from bayesdrive.drivers.idm import IDM
from bayesdrive.drivers.measurement_noise import CAUSE as MEASUREMENT_NOISE
from bayesdrive.drivers.measurement_noise import OLD_NAME_SUFFIX
from bayesdrive.drivers.ovm import OVM

__all__ = ["MODELS", "base_model", "canonical_name", "get_model"]

MODELS = MappingProxyType({model.name: model for model in (IDM, CIDM, GIPPS, OVM)})


def canonical_name(name: str) -> str:
    """``name`` with its base model first ("reaction_delay+idm" -> "idm+reaction_delay");
    a KeyError names the unknown or missing part."""
    parts = [part.strip() for part in name.split("+")]
    if OLD_NAME_SUFFIX in parts:
        raise KeyError(
            f"model {name!r} is a former name: the two measurement-noise models are now one, "
            f"{name.replace(OLD_NAME_SUFFIX, MEASUREMENT_NOISE)!r}, whose sigma_obs prior is "
            "[0, 0.5] m (was [0.005, 1]); results saved under the old name cannot be read, refit them"
        )
    bases = [part for part in parts if part in MODELS]
    unknown = [part for part in parts if part not in MODELS and part not in PARTS]
    if unknown or len(bases) != 1:
        raise KeyError(
            f"unknown driver model {name!r}: "
            + (f"unknown part(s) {unknown}; " if unknown else "")
            + f"a name is one base model of {sorted(MODELS)} joined by '+' to extensions of "
            f"{list(PARTS)}"
        )
    causes = [part for part in parts if part in PARTS]
    problem = composition_problem(causes)
    if problem is not None:
        raise KeyError(f"driver model {name!r} cannot be built: {problem}")
    return "+".join(bases + list(ordered_causes(causes)))


def get_model(name: str) -> DriverModel:
    """The driver model called ``name`` (module docstring); a KeyError says what is unknown or
    which composition rule the name breaks."""
    base, *causes = canonical_name(name).split("+")
    try:
        return compose(MODELS[base], tuple(causes))
    except ValueError as error:
        raise KeyError(str(error)) from None


def base_model(model: DriverModel) -> DriverModel:
    """The base model that ``model`` extends (``model`` itself for a base model). Its parameters
    are the first fields of ``model``'s, and with every extension off ``model`` is it."""
    return MODELS[canonical_name(model.name).split("+")[0]]
