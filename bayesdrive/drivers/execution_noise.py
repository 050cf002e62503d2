r"""Gaussian execution noise on the acceleration: the step law the base models share.

For a model with mean acceleration :math:`\mu` (the IDM's, Gipps', ...) and execution-noise sd
:math:`\sigma` (the paper's :math:`\sigma_{IDM}`), over one step of length :math:`\Delta t`,

.. math::

    a \sim \mathcal N(\mu, \sigma^2), \quad v' = \max(0, v + a\Delta t), \quad
    x' = x + \tfrac{1}{2}(v + v')\Delta t.

While the speed stays positive, :math:`x' = x + v\Delta t + a\Delta t^2/2`, so the position has sd
:math:`\sigma\Delta t^2/2` (the paper's own code used :math:`\sigma\Delta t^2`, a factor 2 off).

**What the likelihood scores.** Next position and next speed are both functions of the one random
acceleration, so their joint density is degenerate (a line in the plane). We score the next
*position increment* :math:`x' - x` (as the paper does), with density
:math:`\mathcal N(v\Delta t + \mu\Delta t^2/2,\ (\sigma\Delta t^2/2)^2)`; the observed next speed
becomes the conditioning state of the following step, and it decides censoring: an observed stop
(:math:`v' \le v_{stop}` = ``STOP_SPEED``, real data holds exact stops and smoothing leaves
values like 1e-5) has probability
:math:`P(v' \le v_{stop}) = \Phi((v_{stop} - v - \mu\Delta t)/(\sigma\Delta t))`, and then the
position carries no further information. Censoring at the same threshold that classifies a stop
keeps the density normalised: stop mass plus the Gaussian over the increments of the moving
outcomes (:math:`v' > v_{stop}`) is exactly 1. In the NGSIM chains the position is exactly the
trapezoid-integrated speed and OpenACC positions are the integrated Doppler speed (see the
readers), so scoring position or speed uses the same information there. Increments are relative
to the current state, so float32 never loses the density on positions of hundreds of metres.

A base model supplies its mean acceleration and parameter specs (one marked ``execution_noise``);
:func:`execution_noise_model` makes it a :class:`~bayesdrive.drivers.base.DriverModel`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jax.scipy.stats import norm

from bayesdrive.drivers.base import (
    DriverModel,
    EgoState,
    ParamSpec,
    car_following_at,
    parameter_noise_sd,
)

__all__ = [
    "STOP_SPEED",
    "IncrementLaw",
    "exact_initial_sample",
    "exact_observation_logpdf",
    "execution_noise_model",
    "increment_law",
    "noisy_step",
    "step_logpdf",
]

# Speeds below 1 mm/s are a stop: smoothing leaves values like 1e-5 where the car stands still.
STOP_SPEED = 1e-3


def noisy_step(key: Array, state: EgoState, mean_acc: Array, sigma: Array, dt: Array) -> EgoState:
    """One step of Gaussian execution noise around ``mean_acc``, speed clipped at 0."""
    acc = mean_acc + sigma * jax.random.normal(key, jnp.shape(mean_acc))
    next_v = jnp.maximum(0.0, state.v + acc * dt)
    return EgoState(x=state.x + 0.5 * (state.v + next_v) * dt, v=next_v)


class IncrementLaw(NamedTuple):
    """The law of one step under :func:`noisy_step`, the one Gaussian increment density every
    density, filter and check uses: a moving step's position increment is N(``mean``, ``sd``^2);
    the step ends in a stop with probability Phi(``stop_z``)."""

    mean: Array
    sd: Array
    stop_z: Array


def increment_law(v: Array, mean_acc: Array, sigma: Array, dt: Array) -> IncrementLaw:
    """:class:`IncrementLaw` of a step from speed ``v`` with mean acceleration ``mean_acc`` and
    execution-noise sd ``sigma``."""
    return IncrementLaw(
        mean=v * dt + 0.5 * mean_acc * dt**2,
        sd=0.5 * sigma * dt**2,
        stop_z=(STOP_SPEED - v - mean_acc * dt) / (sigma * dt),
    )


def step_logpdf(
    state: EgoState,
    next_state: EgoState,
    mean_acc: Array,
    sigma: Array,
    dt: Array,
    *,
    may_stop: bool = True,
) -> Array:
    """Exact log-density of the observed next state under :func:`noisy_step` (module docstring).

    ``may_stop=False`` promises that the observed next speed is above ``STOP_SPEED``: the stop
    probability, whose normal log-CDF costs more than all the rest, is then not computed."""
    law = increment_law(state.v, mean_acc, sigma, dt)
    moving = norm.logpdf(next_state.x - state.x, law.mean, law.sd)
    if not may_stop:
        return moving
    stopped = norm.logcdf(law.stop_z)
    return jnp.where(next_state.v <= STOP_SPEED, stopped, moving)


def exact_observation_logpdf(params, state: EgoState, obs: EgoState) -> Array:
    """The state is observed exactly: the observation carries no density of its own (log 1 = 0)."""
    del params, state, obs
    return jnp.zeros(())


def exact_initial_sample(key: Array, params, obs: EgoState) -> EgoState:
    """With exact observations the first state is the first observation."""
    del key, params
    return obs


def execution_noise_model(
    name: str,
    params_type: type,
    specs: tuple[ParamSpec, ...],
    mean_acceleration,
    noise_sd=None,
    inputs_at=car_following_at,
    scene: str | None = None,
) -> DriverModel:
    """A driver model that applies ``mean_acceleration`` with Gaussian execution noise of sd
    ``noise_sd(params, state)`` (default: the parameter ``specs`` mark ``execution_noise``;
    :func:`noisy_step`, scored exactly by :func:`step_logpdf`), state observed exactly, reading the
    inputs ``inputs_at`` builds, which need the series' ``scene`` part beyond car following (None:
    none). The base models and the criticism's Gaussian extensions differ only in their mean
    acceleration and inputs (and, for speed-dependent noise, the sd)."""
    noise_sd = parameter_noise_sd(specs) if noise_sd is None else noise_sd

    def transition_sample(key: Array, params, state: EgoState, inputs) -> EgoState:
        mean_acc = mean_acceleration(params, state, inputs)
        return noisy_step(key, state, mean_acc, noise_sd(params, state), inputs.dt)

    def transition_logpdf(params, state: EgoState, next_state: EgoState, inputs) -> Array:
        mean_acc = mean_acceleration(params, state, inputs)
        return step_logpdf(state, next_state, mean_acc, noise_sd(params, state), inputs.dt)

    def series_logpdf(params, steps) -> Array:
        # Stops are rare in car-following data and the stop term's normal log-CDF costs more than
        # the rest of the density: a series without a stop skips it.
        def scored(may_stop: bool) -> Array:
            def one(v, next_v, dx, inputs):
                state = EgoState(jnp.zeros_like(v), v)
                mean_acc = mean_acceleration(params, state, inputs)
                sd = noise_sd(params, state)
                return step_logpdf(
                    state, EgoState(dx, next_v), mean_acc, sd, inputs.dt, may_stop=may_stop
                )

            return jax.vmap(one)(steps.v, steps.next_v, steps.dx, steps.inputs)

        any_stop = jnp.any(steps.next_v <= STOP_SPEED)
        return jax.lax.cond(any_stop, lambda: scored(True), lambda: scored(False))

    return DriverModel(
        name=name,
        params_type=params_type,
        specs=specs,
        mean_acceleration=mean_acceleration,
        transition_sample=transition_sample,
        transition_logpdf=transition_logpdf,
        observation_logpdf=exact_observation_logpdf,
        initial_sample=exact_initial_sample,
        inputs_at=inputs_at,
        series_logpdf=series_logpdf,
        scene=scene,
        noise_sd=noise_sd,
    )
