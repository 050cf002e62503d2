"""Model extensions, one cause of misfit each, and the registry the criticism uses.

Each extension wraps a car-following base model (see :mod:`.compose`) and adds parameters with
documented priors whose defaults switch it off, so the base model is nested in every extension.
:data:`EXTENSIONS` maps the cause name that ``bayesdrive criticize`` reports to the wrapper.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from types import MappingProxyType

from bayesdrive.drivers import measurement_noise
from bayesdrive.drivers.base import DriverModel
from bayesdrive.drivers.extensions import (
    autocorrelated_noise,
    cut_in,
    drifting_parameters,
    reaction_delay,
    second_leader,
    speed_dependent_noise,
)
from bayesdrive.drivers.extensions.compose import ExtendedModel

__all__ = ["CAUSES", "EXTENSIONS", "NO_CAUSE", "as_extended", "extend", "with_measurement_noise"]

NO_CAUSE = "none"


@functools.cache
def with_measurement_noise(base: DriverModel) -> ExtendedModel:
    """The one measurement-noise model (:mod:`bayesdrive.drivers.measurement_noise`) as the
    extension for its cause; it keeps the base model's inputs, so it wraps any base model."""
    model = measurement_noise.with_measurement_noise(base)
    return ExtendedModel(measurement_noise.CAUSE, base, model, (measurement_noise.SIGMA_OBS.name,))


EXTENSIONS: MappingProxyType[str, Callable[[DriverModel], ExtendedModel]] = MappingProxyType(
    {
        reaction_delay.CAUSE: reaction_delay.with_reaction_delay,
        autocorrelated_noise.CAUSE: autocorrelated_noise.with_autocorrelated_noise,
        speed_dependent_noise.CAUSE: speed_dependent_noise.with_speed_dependent_noise,
        second_leader.CAUSE: second_leader.with_second_leader_anticipation,
        cut_in.CAUSE: cut_in.with_cut_in_heuristic,
        drifting_parameters.CAUSE: drifting_parameters.with_drifting_time_gap,
        measurement_noise.CAUSE: with_measurement_noise,
    }
)
CAUSES = tuple(EXTENSIONS)


@functools.cache
def as_extended(base: DriverModel) -> ExtendedModel:
    """The base model itself in the :class:`ExtendedModel` form (cause "none", nothing added)."""
    return ExtendedModel(NO_CAUSE, base, base, ())


def extend(cause: str, base: DriverModel) -> ExtendedModel:
    """``base`` extended for ``cause`` (or itself for "none"); a KeyError lists the causes."""
    if cause == NO_CAUSE:
        return as_extended(base)
    try:
        wrap = EXTENSIONS[cause]
    except KeyError:
        raise KeyError(f"unknown cause {cause!r}; known causes: {list(CAUSES)}") from None
    return wrap(base)
