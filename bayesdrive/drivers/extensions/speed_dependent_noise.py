r"""Speed-dependent execution noise: the acceleration error grows with speed.

.. math::

    a \sim N\big(a_{base},\ \sigma(v)^2\big), \qquad
    \sigma(v) = \sigma\,\frac{1 + k\, v}{1 + k\, v_{ref}},

with :math:`\sigma` the wrapped model's own noise sd (its ``noise_sd``) and :math:`k` the relative
increase per m/s of the current speed over the noise at standstill (k = 0.1 doubles it from 0 to
10 m/s). :math:`\sigma` is the noise at the reference speed :math:`v_{ref}` =
``REFERENCE_SPEED_MPS`` (10 m/s, a round speed fixed in advance, not read from data). Why not the
noise at standstill: followers seldom stand still, so the data pin the noise at the speeds they
drive, and a standstill level trades off against the slope along a curved ridge
(sigma (1 + k v) constant) that emcee's stretch moves cross slowly
(``reports/convergence/extensions_pilot.md``); the noise at a driven speed is what the data
measure. With k = 0 the model is the wrapped one.

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

__all__ = [
    "CAUSE",
    "REFERENCE_SPEED_MPS",
    "SPEED_NOISE_SPECS",
    "speed_dependent_sd",
    "with_speed_dependent_noise",
]

CAUSE = "speed_dependent_noise"
# The speed at which the wrapped model's sigma is the noise sd (module docstring).
REFERENCE_SPEED_MPS = 10.0
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
    """sigma(v) = sigma (1 + k v) / (1 + k v_ref) at the state's current speed, sigma ``base``'s
    noise sd at the reference speed (module docstring)."""

    def noise_sd(params, state) -> Array:
        sigma = base.noise_sd(base_params(base, params), state)
        slope = params.noise_speed_slope
        return sigma * (1.0 + slope * state.v) / (1.0 + slope * REFERENCE_SPEED_MPS)

    return noise_sd


@functools.cache
def with_speed_dependent_noise(base: DriverModel) -> ExtendedModel:
    """``base`` (any exactly observed model with white noise, a ``mean`` extension included) with
    execution noise sd sigma (1 + k v) / (1 + k v_ref) (module docstring); it reads what ``base``
    reads."""
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
