r"""Speed-dependent execution noise: the acceleration error grows with speed.

.. math::

    a \sim N\big(a_{base},\ \sigma(v)^2\big), \qquad \sigma(v) = \sigma\,(1 + k\, v),

with :math:`\sigma` the wrapped model's own noise sd (its ``noise_sd``), so it is the noise at
standstill and :math:`k` the relative increase per m/s of the
current speed (k = 0.1 doubles the noise at 10 m/s).

=================  ====  =======  ============  =====================================
name               unit  default  prior bounds  meaning
=================  ====  =======  ============  =====================================
noise_speed_slope  s/m   0.0      [0, 0.5]      relative noise increase per m/s
=================  ====  =======  ============  =====================================
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

from jax import Array

from bayesdrive.drivers.base import DriverModel, EgoState, ParamSpec
from bayesdrive.drivers.extensions.compose import (
    ExtendedModel,
    base_params,
    check_white_noise,
    gaussian_extension,
)

__all__ = ["CAUSE", "SPEED_NOISE_SPECS", "speed_dependent_sd", "with_speed_dependent_noise"]

CAUSE = "speed_dependent_noise"
SPEED_NOISE_SPECS = (
    ParamSpec(
        "noise_speed_slope",
        "s/m",
        0.0,
        0.0,
        0.5,
        "relative noise increase per m/s",
        grid_step=0.025,
    ),
)


def speed_dependent_sd(base: DriverModel) -> Callable[[Any, Any], Array]:
    """sigma(v) = sigma (1 + k v) at the state's current speed, sigma ``base``'s noise sd."""

    def noise_sd(params, state) -> Array:
        sigma = base.noise_sd(base_params(base, params), state)
        return sigma * (1.0 + params.noise_speed_slope * state.v)

    return noise_sd


@functools.cache
def with_speed_dependent_noise(base: DriverModel) -> ExtendedModel:
    """``base`` (any exactly observed model with white noise, a ``mean`` extension included) with
    execution noise sd sigma (1 + k v) (module docstring); it reads what ``base`` reads."""
    check_white_noise(base, CAUSE)

    def mean_acceleration(params, state: EgoState, inputs) -> Array:
        return base.mean_acceleration(base_params(base, params), state, inputs)

    return gaussian_extension(
        base,
        CAUSE,
        SPEED_NOISE_SPECS,
        mean_acceleration,
        noise_sd=speed_dependent_sd(base),
        reads_history=base.reads_history,
        reads=base.inputs_at,
    )
