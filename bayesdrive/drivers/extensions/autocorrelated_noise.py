r"""Autocorrelated execution noise: an Ornstein-Uhlenbeck error reaching the acceleration through a
first-order lag, sampled.

With :math:`u_t` the deviation of the applied acceleration from the base rule, :math:`T_e`
(``noise_time_s``) the error's correlation time and :math:`T_l` (``noise_lag_s``) the time
constant of the lag it passes through, both in seconds and sampled every :math:`\Delta t`,

.. math::

    u_t = (r_e + r_l)\, u_{t-1} - r_e r_l\, u_{t-2} + s\, z_t, \quad z_t \sim N(0, 1), \qquad
    r_e = \frac{T_e}{T_e + \Delta t}, \quad r_l = \frac{T_l}{T_l + \Delta t}, \qquad
    a_t = a_{base,t} + u_t,

an AR(2) with roots :math:`r_e` and :math:`r_l`, whose innovation sd
:math:`s = \sigma \sqrt{(1 - r_e r_l)(1 - r_e^2)(1 - r_l^2) / (1 + r_e r_l)}` keeps the base model's
marginal sd :math:`\sigma`. Each root is the implicit (backward Euler) discretisation of a
first-order process, :math:`de = -e/T_e\,dt + \ldots` for the error and
:math:`du = (e - u)/T_l\,dt` for the lag, so the error's correlation after :math:`k` seconds
tends to :math:`\exp(-k / T_e)` as the sampling gets finer. The per-step roots are derived from
each step's own :math:`\Delta t`, so fits at 10 Hz and at 2 Hz estimate the same parameters.
:math:`T_l = 0` is the Ornstein-Uhlenbeck error alone (an AR(1) of coefficient :math:`r_e`), and
:math:`T_e = T_l = 0` white noise (the base model, nested). The exact discretisation
:math:`\exp(-\Delta t/T_e)` is flat to every order at :math:`T_e = 0`: the criticism's score test
of the extension at its off value (:func:`bayesdrive.criticism.checks.score_check`) would have no
power, whereas this slope there is :math:`1/\Delta t`, so the test is the one in :math:`r_e`.

**Why the lag.** An error fitted as an AR(1) one step ahead on 10 Hz data takes a per-step
coefficient near 0.98 and forecasts positions 1-5 s ahead too surely: the residuals of the
measured trajectories have a second, fast root (``reports/noise_horizons.md``). The lag carries
it, whether it comes from the vehicle's response to the pedal or from the data's smoothing, so
the persistent error keeps the correlation time the forecast needs.

**Bounds and prior.** :math:`T_e` is uniform on [0, 5] s. An execution error (the foot off the
intended pedal position) is a motor deviation drivers correct within seconds; one that persists
longer is no execution error but a changed intention (a drifting parameter), and a residual that
persists for tens of seconds carries the last observed error through a whole forecast, which then
forecasts like constant acceleration. At 5 s the error's memory is :math:`e^{-1}` after the 5 s
forecast horizon, and :math:`r_e \le 0.980` at 10 Hz. :math:`T_l` is uniform on [0, 0.5] s, the
range of a car's response to its pedals. The two roots play symmetric parts in the AR(2) (an
error of correlation time 0.3 s without lag is the same process as a 0.3 s lag of white noise),
and the lag's upper bound keeps them apart wherever the error persists longer than 0.5 s.

**Exact likelihood with observed states.** The state carries the last two residuals
(:class:`NoiseMemoryState`). With exactly observed positions and speeds, they are observed too:
:math:`u_{t-1} = \hat a_{t-1} - a_{base,t-1}`, where :math:`\hat a = 2(\Delta x - v\,\Delta
t)/\Delta t^2` is the acceleration implied by the observed position increment (the quantity the
base likelihood scores) and the base rule is evaluated on that step's own inputs
(:class:`NoiseMemoryInputs`: the wrapped model's inputs at this step and the two before, so any
exactly observed model with white noise can be wrapped, a reaction delay included).
:func:`with_autocorrelated_noise`'s ``lift`` recovers them, so each step is scored exactly given
the observed past.

**Stops and limits.** A step that ends in a stop or at a physical limit censors its acceleration
(the speed is clipped at 0, the acceleration at the floor or the ceiling:
:mod:`bayesdrive.drivers.execution_noise`), so its residual is unknown. The state counts the
residuals known since (``known``: 0, 1 or 2), and the step's distribution conditions on those
alone: on two, the AR(2) above; on one, its lag-one regression (coefficient
:math:`(r_e + r_l)/(1 + r_e r_l)`); on none, the stationary distribution (mean
:math:`a_{base}`, sd :math:`\sigma`). Simulation does the same, so sampler and density describe
one process.

============  ====  =======  ============  =================================================
name          unit  default  prior bounds  meaning
============  ====  =======  ============  =================================================
noise_time_s  s     0.0      [0, 5]        correlation time of the acceleration error (0:
                                           white noise, the base model)
noise_lag_s   s     0.0      [0, 0.5]      time constant of the lag the error passes
                                           through (0: no lag)
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
    "MAX_NOISE_LAG_S",
    "MAX_NOISE_TIME_S",
    "NoiseMemoryInputs",
    "NoiseMemoryState",
    "error_regression",
    "implied_acceleration",
    "step_correlation",
    "with_autocorrelated_noise",
]

CAUSE = "autocorrelated_noise"
# Upper bounds of the correlation time and of the lag (module docstring: why these).
MAX_NOISE_TIME_S = 5.0
MAX_NOISE_LAG_S = 0.5
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
    ParamSpec(
        "noise_lag_s",
        "s",
        0.0,
        0.0,
        MAX_NOISE_LAG_S,
        "time constant of the lag the acceleration error passes through",
        grid_step=0.1,
    ),
)


def step_correlation(noise_time_s: Array, dt: Array) -> Array:
    """The lag-one-step correlation T / (T + dt) of an error with correlation time T seconds."""
    return noise_time_s / (noise_time_s + dt)


class NoiseMemoryState(NamedTuple):
    """Position x (m, relative to the current step), speed v (m/s), the last two acceleration
    residuals (m/s^2; ``residual`` the last, ``earlier_residual`` the one before) and how many of
    them are known since the last stop or limit censored one (0.0, 1.0 or 2.0)."""

    x: Array
    v: Array
    residual: Array
    earlier_residual: Array
    known: Array


class NoiseMemoryInputs(NamedTuple):
    """What the autocorrelated noise reads: the wrapped model's inputs at this step (``now``) and
    at the two steps before (``previous``, ``earlier``), the ego's speed at those steps (m/s) and
    its position increments over them (m)."""

    now: Any
    previous: Any
    previous_v: Array
    previous_dx: Array
    earlier: Any
    earlier_v: Array
    earlier_dx: Array

    @property
    def dt(self) -> Array:
        return self.now.dt


def error_regression(noise_time_s: Array, noise_lag_s: Array, dt: Array, known: Array):
    """The error's regression on the residuals known (module docstring): the coefficients of the
    last and the one before, and the remaining variance as a share of the marginal one."""
    r_e, r_l = step_correlation(noise_time_s, dt), step_correlation(noise_lag_s, dt)
    lag_one = (r_e + r_l) / (1.0 + r_e * r_l)
    both = known >= 2.0
    last = jnp.where(both, r_e + r_l, jnp.where(known >= 1.0, lag_one, 0.0))
    before = jnp.where(both, -r_e * r_l, 0.0)
    innovation = (1.0 - r_e * r_l) * (1.0 - r_e**2) * (1.0 - r_l**2) / (1.0 + r_e * r_l)
    share = jnp.where(both, innovation, jnp.where(known >= 1.0, 1.0 - lag_one**2, 1.0))
    return last, before, share


@functools.cache
def with_autocorrelated_noise(base: DriverModel) -> ExtendedModel:
    """``base`` (any exactly observed model with white noise of sd ``sigma``, its ``noise_sd``, a
    ``mean`` extension included) with execution noise of correlation time ``noise_time_s`` through
    a lag of ``noise_lag_s`` (module docstring)."""
    check_white_noise(base, CAUSE)
    specs = extended_specs(base, AR_SPECS)

    def base_mean(params, v: Array, inputs) -> Array:
        return base.mean_acceleration(
            base_params(base, params), EgoState(jnp.zeros_like(v), v), inputs
        )

    def conditional(params, state: NoiseMemoryState, inputs: NoiseMemoryInputs):
        """Mean and sd of this step's acceleration given the residuals known."""
        last, before, share = error_regression(
            params.noise_time_s, params.noise_lag_s, inputs.dt, state.known
        )
        memory = last * state.residual + before * state.earlier_residual
        mean_acc = base_mean(params, state.v, inputs.now) + memory
        sigma = base.noise_sd(base_params(base, params), EgoState(state.x, state.v))
        return mean_acc, sigma * jnp.sqrt(share)

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
        known = jnp.where(censored, 0.0, jnp.minimum(state.known + 1.0, 2.0))
        return NoiseMemoryState(
            moved.x, moved.v, (known > 0) * residual, (known > 1) * state.residual, known
        )

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

    def observed_residual(params, v_before: Array, v_after: Array, dx: Array, step_inputs, dt):
        """The residual of an observed step and whether a stop or a limit censored it."""
        applied = implied_acceleration(v_before, dx, dt)
        residual = applied - base_mean(params, v_before, step_inputs)
        ceiling = acceleration_ceiling(v_before, step_inputs)
        return residual, censored_step(v_before, v_after, dx, dt, ceiling)

    def lift(params, state: EgoState, inputs: NoiseMemoryInputs) -> NoiseMemoryState:
        dt = inputs.dt
        residual, last_censored = observed_residual(
            params, inputs.previous_v, state.v, inputs.previous_dx, inputs.previous, dt
        )
        earlier, earlier_censored = observed_residual(
            params, inputs.earlier_v, inputs.previous_v, inputs.earlier_dx, inputs.earlier, dt
        )
        known = jnp.where(last_censored, 0.0, jnp.where(earlier_censored, 1.0, 2.0))
        known = known.astype(state.v.dtype)
        return NoiseMemoryState(
            state.x, state.v, (known > 0) * residual, (known > 1) * earlier, known
        )

    def initial_sample(key: Array, params, obs: EgoState) -> NoiseMemoryState:
        del key, params
        zero = jnp.zeros_like(obs.v)
        return NoiseMemoryState(obs.x, obs.v, zero, zero, zero)

    def inputs_at(series: Series, j: Array, history: int) -> NoiseMemoryInputs:
        before, earlier = jnp.maximum(j - 1, 0), jnp.maximum(j - 2, 0)
        return NoiseMemoryInputs(
            now=base.inputs_at(series, j, history),
            previous=base.inputs_at(series, before, history),
            previous_v=series.v[before],
            previous_dx=series.dx[before],
            earlier=base.inputs_at(series, earlier, history),
            earlier_v=series.v[earlier],
            earlier_dx=series.dx[earlier],
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
