r"""Autocorrelated execution noise: the acceleration error, a sampled Ornstein-Uhlenbeck process.

With :math:`e_t` the deviation of the applied acceleration from the base rule and :math:`T_e`
(``noise_time_s``) its correlation time in seconds, sampled every :math:`\Delta t`,

.. math::

    e_t = \rho\, e_{t-1} + \sqrt{1 - \rho^2}\,\sigma\, z_t, \quad z_t \sim N(0, 1), \qquad
    \rho = \frac{T_e}{T_e + \Delta t}, \qquad a_t = a_{base,t} + e_t,

a stationary AR(1) with the base model's marginal sd :math:`\sigma`: the implicit (backward
Euler) discretisation of the Ornstein-Uhlenbeck process :math:`de = -e/T_e\,dt + \ldots`, so the
error's correlation after :math:`k` seconds, :math:`(1 + \Delta t/T_e)^{-k/\Delta t}`, tends to
:math:`\exp(-k / T_e)` as the sampling gets finer. The per-step :math:`\rho` is derived from each step's own
:math:`\Delta t`, so fits at 10 Hz and at 2 Hz estimate the same parameter. :math:`T_e = 0` is
white noise (the base model, nested). The exact discretisation :math:`\exp(-\Delta t/T_e)` is
flat to every order at :math:`T_e = 0`: the criticism's score test of the extension at its off
value (:func:`bayesdrive.criticism.checks.score_check`) would have no power, whereas this slope
there is :math:`1/\Delta t`, so the test is the one in :math:`\rho`.

**Bounds and prior.** :math:`T_e` is uniform on [0, 5] s. An execution error (the foot off the
intended pedal position) is a motor deviation drivers correct within seconds; one that persists
longer is no execution error but a changed intention (a drifting parameter), and a residual that
persists for tens of seconds carries the last observed error through a whole forecast, which then
forecasts like constant acceleration. At 5 s the error's memory is :math:`e^{-1}` after the 5 s
forecast horizon, and :math:`\rho \le 0.980` at 10 Hz.

**Exact likelihood with observed states.** The state carries the last residual
(:class:`NoiseMemoryState`). With exactly observed positions and speeds, the previous step's
residual is observed too: :math:`e_{t-1} = \hat a_{t-1} - a_{base,t-1}`, where
:math:`\hat a = 2(\Delta x - v\,\Delta t)/\Delta t^2` is the acceleration implied by the observed
position increment (the quantity the base likelihood scores) and the base rule is evaluated on
the previous step's own inputs (:class:`NoiseMemoryInputs`: the wrapped model's inputs at this
step and the one before, so any exactly observed model with white noise can be wrapped, a
reaction delay included). :func:`with_autocorrelated_noise`'s ``lift`` recovers it, so each step
is scored exactly given the observed past.

**Stops and limits.** A step that ends in a stop or at a physical limit censors its acceleration
(the speed is clipped at 0, the acceleration at the floor or the ceiling:
:mod:`bayesdrive.drivers.execution_noise`), so the residual is unknown afterwards; the process
then restarts from its stationary distribution (``known = 0``: mean :math:`a_{base}`, sd
:math:`\sigma`). Simulation does the same, so sampler and density describe one process.

============  ====  =======  ============  =================================================
name          unit  default  prior bounds  meaning
============  ====  =======  ============  =================================================
noise_time_s  s     0.0      [0, 5]        correlation time of the acceleration error (0:
                                           white noise, the base model)
============  ====  =======  ============  =================================================
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax.numpy as jnp
from jax import Array

from bayesdrive.drivers.base import DriverModel, EgoState, ParamSpec, Series
from bayesdrive.drivers.execution_noise import (
    acceleration_ceiling,
    censored_observation,
    censored_step,
    implied_acceleration,
    noisy_step,
    step_logpdf,
)
from bayesdrive.drivers.extensions.compose import (
    ExtendedModel,
    base_params,
    check_white_noise,
    extended_specs,
    state_extension,
)

__all__ = [
    "AR_SPECS",
    "CAUSE",
    "MAX_NOISE_TIME_S",
    "NoiseMemoryInputs",
    "NoiseMemoryState",
    "implied_acceleration",
    "step_correlation",
    "with_autocorrelated_noise",
]

CAUSE = "autocorrelated_noise"
# Upper bound of the correlation time (module docstring: why 5 s).
MAX_NOISE_TIME_S = 5.0
AR_SPECS = (
    ParamSpec(
        "noise_time_s",
        "s",
        0.0,
        0.0,
        MAX_NOISE_TIME_S,
        "correlation time of the acceleration error",
        grid_step=0.1,
    ),
)


def step_correlation(noise_time_s: Array, dt: Array) -> Array:
    """The lag-one-step correlation T / (T + dt) of an error with correlation time T seconds."""
    return noise_time_s / (noise_time_s + dt)


class NoiseMemoryState(NamedTuple):
    """Position x (m, relative to the current step), speed v (m/s), the last acceleration residual
    (m/s^2) and whether it is known (1.0) or censored by a stop (0.0)."""

    x: Array
    v: Array
    residual: Array
    known: Array


class NoiseMemoryInputs(NamedTuple):
    """What the autocorrelated noise reads: the wrapped model's inputs at this step (``now``) and
    at the step before (``previous``), the ego's speed then (m/s) and its position increment over
    that step (m)."""

    now: Any
    previous: Any
    previous_v: Array
    previous_dx: Array

    @property
    def dt(self) -> Array:
        return self.now.dt


@functools.cache
def with_autocorrelated_noise(base: DriverModel) -> ExtendedModel:
    """``base`` (any exactly observed model with white noise of sd ``sigma``, its ``noise_sd``, a
    ``mean`` extension included) with Ornstein-Uhlenbeck execution noise of correlation time
    ``noise_time_s`` (module docstring)."""
    check_white_noise(base, CAUSE)
    specs = extended_specs(base, AR_SPECS)

    def base_mean(params, v: Array, inputs) -> Array:
        return base.mean_acceleration(
            base_params(base, params), EgoState(jnp.zeros_like(v), v), inputs
        )

    def conditional(params, state: NoiseMemoryState, inputs: NoiseMemoryInputs):
        """Mean and sd of this step's acceleration given the last residual."""
        memory = state.known * step_correlation(params.noise_time_s, inputs.dt)
        mean_acc = base_mean(params, state.v, inputs.now) + memory * state.residual
        sigma = base.noise_sd(base_params(base, params), EgoState(state.x, state.v))
        sd = sigma * jnp.sqrt(1.0 - memory**2)
        return mean_acc, sd

    def mean_acceleration(params, state: NoiseMemoryState, inputs: NoiseMemoryInputs) -> Array:
        return conditional(params, state, inputs)[0]

    def transition_sample(key: Array, params, state: NoiseMemoryState, inputs: NoiseMemoryInputs):
        mean_acc, sd = conditional(params, state, inputs)
        ceiling = acceleration_ceiling(state.v, inputs.now)
        moved = noisy_step(key, EgoState(state.x, state.v), mean_acc, sd, inputs.dt, ceiling)
        dx = moved.x - state.x
        residual = implied_acceleration(state.v, dx, inputs.dt) - base_mean(
            params, state.v, inputs.now
        )
        censored = censored_step(state.v, moved.v, dx, inputs.dt, ceiling)
        known = (~censored).astype(moved.v.dtype)
        return NoiseMemoryState(moved.x, moved.v, known * residual, known)

    def transition_logpdf(
        params, state: NoiseMemoryState, next_state, inputs, *, may_be_censored: bool | Array = True
    ) -> Array:
        mean_acc, sd = conditional(params, state, inputs)
        ceiling = acceleration_ceiling(state.v, inputs.now)
        ego = EgoState(state.x, state.v)
        return step_logpdf(
            ego, next_state, mean_acc, sd, inputs.dt, ceiling, may_be_censored=may_be_censored
        )

    def censored(state: EgoState, next_state: EgoState, inputs: NoiseMemoryInputs) -> Array:
        return censored_observation(state, next_state, inputs.now)

    def lift(params, state: EgoState, inputs: NoiseMemoryInputs) -> NoiseMemoryState:
        before = inputs.previous_v
        applied = implied_acceleration(before, inputs.previous_dx, inputs.dt)
        residual = applied - base_mean(params, before, inputs.previous)
        ceiling = acceleration_ceiling(before, inputs.previous)
        censored = censored_step(before, state.v, inputs.previous_dx, inputs.dt, ceiling)
        known = (~censored).astype(state.v.dtype)
        return NoiseMemoryState(state.x, state.v, known * residual, known)

    def initial_sample(key: Array, params, obs: EgoState) -> NoiseMemoryState:
        del key, params
        return NoiseMemoryState(obs.x, obs.v, jnp.zeros_like(obs.v), jnp.zeros_like(obs.v))

    def inputs_at(series: Series, j: Array, history: int) -> NoiseMemoryInputs:
        before = jnp.maximum(j - 1, 0)
        return NoiseMemoryInputs(
            now=base.inputs_at(series, j, history),
            previous=base.inputs_at(series, before, history),
            previous_v=series.v[before],
            previous_dx=series.dx[before],
        )

    return state_extension(
        base,
        CAUSE,
        specs,
        mean_acceleration=mean_acceleration,
        transition_sample=transition_sample,
        transition_logpdf=transition_logpdf,
        censored=censored,
        initial_sample=initial_sample,
        inputs_at=inputs_at,
        lift=lift,
        reads_history=True,
    )
