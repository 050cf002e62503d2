r"""Measurement noise on recorded positions (speeds and gaps recorded exactly).

The situation of GNSS positions beside Doppler speeds and radar gaps: the recorded position is
:math:`y_t = x_t + \varepsilon_t` with white noise :math:`\varepsilon_t \sim N(0, s^2)`, while the
speeds and bumper gaps are exact, and the dynamics are the base model's. Every model is scored on
the same thing: the one-step predictive density of the next recorded position increment given
everything recorded so far (positions and speeds up to now), so the gain against the base model is
a fair comparison of forecasts.

**Exact filter.** With exact speeds the true increment of a step is known once the next speed is
recorded (:math:`\Delta x_t = (v_t + v_{t+1})\Delta t/2`, the base models' kinematics), so each
step reveals the noise difference :math:`d_t = \varepsilon_{t+1} - \varepsilon_t`. The noise level
itself is a hidden scalar with a Gaussian filter (``filter``): :math:`\varepsilon_t \mid
\text{past} \sim N(m_t, P_t)`, starting from :math:`N(0, s^2)` at the first step of a stretch of
data (a gap in the data restarts it). The predictive density of the recorded increment is

.. math::

    y_{t+1} - y_t \sim N\big(v_t\Delta t + a_{base}\Delta t^2/2 - m_t,\ (\sigma\Delta t^2/2)^2 + s^2
    + P_t\big),

and afterwards :math:`\varepsilon_{t+1}` combines its prior :math:`N(0, s^2)` with
:math:`\varepsilon_t + d_t`: :math:`m_{t+1} = (m_t + d_t) s^2/(s^2 + P_t)`,
:math:`P_{t+1} = s^2 P_t/(s^2 + P_t)`. The base model is nested exactly at :math:`s = 0`. A step
that ends in a stop is scored by the base model's stop probability (the position adds nothing to
a stop, as for the base model). The noise-free dynamics are the base model's, so simulation and
rollouts use them unchanged. (:mod:`bayesdrive.drivers.measurement_noise` with the latent-state
particle filter covers noisy positions *without* exact speeds; with exact speeds this filter is
exact and cheap.)

==============  ====  =======  ============  ==============================================
name            unit  default  prior bounds  meaning
==============  ====  =======  ============  ==============================================
position_noise  m     0.0      [0, 0.5]      sd of the white noise on recorded positions
==============  ====  =======  ============  ==============================================
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
from jax import Array
from jax.scipy.stats import norm

from bayesdrive.drivers.base import DriverModel, EgoState, ParamSpec
from bayesdrive.drivers.extensions.compose import (
    ExtendedModel,
    base_params,
    check_base,
    extended_specs,
    params_type,
)
from bayesdrive.drivers.extensions.inputs import ExtendedInputs, inputs_at
from bayesdrive.drivers.idm import STOP_SPEED, step_logpdf

__all__ = ["CAUSE", "POSITION_NOISE_SPECS", "with_position_noise"]

CAUSE = "measurement_noise"
POSITION_NOISE_SPECS = (
    ParamSpec("position_noise", "m", 0.0, 0.0, 0.5, "sd of white noise on recorded positions"),
)


@functools.cache
def with_position_noise(base: DriverModel) -> ExtendedModel:
    """``base`` observed through white noise on positions (module docstring)."""
    check_base(base, CAUSE)
    specs = extended_specs(base, POSITION_NOISE_SPECS)

    def mean_acceleration(params, state: EgoState, inputs: ExtendedInputs) -> Array:
        return base.mean_acceleration(base_params(base, params), state, inputs.car_following)

    def transition_sample(key: Array, params, state: EgoState, inputs: ExtendedInputs):
        return base.transition_sample(key, base_params(base, params), state, inputs.car_following)

    def transition_logpdf(params, state: EgoState, next_state, inputs: ExtendedInputs) -> Array:
        own = base_params(base, params)
        return base.transition_logpdf(own, state, next_state, inputs.car_following)

    def observation_logpdf(params, state: EgoState, obs: EgoState) -> Array:
        return norm.logpdf(obs.x, state.x, params.position_noise)

    def kalman(params, steps: Any) -> Array:
        """One-step predictive log densities of one vehicle's steps (T,) (module docstring).

        The filter's recursion has a closed form, so it is vectorised over steps instead of
        scanned: in a stretch of data, at its k-th step (k = 0 first), P = s^2/(k + 1) and
        (k + 1) m = sum over the stretch's earlier steps i of (k_i + 1) d_i.
        """
        dt = steps.inputs.dt[0]
        noise_var = params.position_noise**2
        dynamics_sd = 0.5 * params.sigma * dt**2
        index = jnp.arange(steps.v.shape[0])
        usable = steps.mask > 0
        starts = usable & ~jnp.concatenate([jnp.zeros(1, bool), usable[:-1]])
        first = jax.lax.cummax(jnp.where(starts, index, 0))
        rank = (index - first).astype(steps.v.dtype)  # k: steps since the stretch began
        difference = steps.dx - 0.5 * (steps.v + steps.next_v) * dt  # d = e[t+1] - e[t]
        weighted = jnp.where(usable, (rank + 1.0) * difference, 0.0)
        before = jnp.cumsum(weighted) - weighted  # sum over earlier steps, exclusive
        # With s = 0 the noise is identically 0: the base model exactly.
        mean = jnp.where(noise_var > 0, (before - before[first]) / (rank + 1.0), 0.0)
        var = noise_var / (rank + 1.0)

        def one(inputs, v, next_v, dx, mean, var):
            state = EgoState(jnp.zeros_like(v), v)
            rule = mean_acceleration(params, state, inputs)
            predicted = v * dt + 0.5 * rule * dt**2 - mean
            moving = norm.logpdf(dx, predicted, jnp.sqrt(dynamics_sd**2 + noise_var + var))
            stopped = step_logpdf(state, EgoState(dx, next_v), rule, params.sigma, dt)
            return jnp.where(next_v <= STOP_SPEED, stopped, moving)

        return jax.vmap(one)(steps.inputs, steps.v, steps.next_v, steps.dx, mean, var)

    model = DriverModel(
        name=f"{base.name}+{CAUSE}",
        params_type=params_type("MeasurementNoiseParams", specs),
        specs=specs,
        mean_acceleration=mean_acceleration,
        transition_sample=transition_sample,
        transition_logpdf=transition_logpdf,
        observation_logpdf=observation_logpdf,
        initial_sample=base.initial_sample,
        inputs_at=inputs_at,
        filter=kalman,
    )
    return ExtendedModel(CAUSE, base, model, ("position_noise",))
