r"""Drifting parameters: the desired time gap wanders as a random walk during the drive.

The time gap is :math:`\tau_t = \tau + u_t` with a hidden offset that starts at 0 and moves by

.. math::

    u_{t+1} = u_t + q\sqrt{\Delta t}\,\xi_t, \qquad \xi_t \sim N(0, 1),

before each step's acceleration :math:`a_t \sim N(a_{base}(\tau + u_{t+1}), \sigma^2)` (the drifted
time gap is kept inside the prior box of :math:`\tau`). A drifting parameter is a hidden state: the
one-step predictive density of the observed step needs a state filter. Here it is a Kalman filter
on the scalar offset (``filter``) that linearises the base rule in :math:`u` by a central
difference, :math:`J = [a(\bar u + h) - a(\bar u - h)] / 2h` with ``DIFFERENCE_STEP`` :math:`h`,
not by the derivative at the mean: the rule has kinks in :math:`u` (the IDM's floored dynamic gap,
the clip to the box), :math:`J` enters the predictive variance, and a derivative that jumps at a
kink made the likelihood jump with it, which stalls gradient samplers
(``reports/convergence/drifting_nuts.md``); the difference is continuous wherever the rule is. The
filtered mean is projected onto the box after each update: outside it the rule is flat, :math:`J`
would be 0 and the filter would stop learning the offset for good, and whether it ever left that
trap turned on parameter changes of 1e-6. The
difference's step is fixed, not the filtered sd (a divided-difference filter's): a slope that depends on the
variance feeds the variance recursion back on itself, and its gradient then overflowed over a
series. The observed implied acceleration :math:`\hat a = 2(\Delta x - v\Delta t)/\Delta t^2` updates
the offset, and the predictive density of the position increment has variance
:math:`(\Delta t^2/2)^2 (J^2 P + \sigma^2)` around the rule at the
filtered mean. With :math:`q = 0` it is the base model exactly; otherwise it is an approximation
whose error is second order in the offset's uncertainty (small: the offset moves by
:math:`q\sqrt{\Delta t}` per step) and in :math:`h` where the rule is smooth. A step that ends in a stop censors its acceleration and does not
update the filter. The filter restarts (offset 0, known) after a gap in the data. A forecast from
observed data starts from the law the same filter gives of the offset over the vehicle's steps
before the window (``filtered_start``), not from the fitted time gap; the latent-state
particle filter of :mod:`bayesdrive.inference.engines.pmmh` targets noisy positions, not exactly observed
states with a hidden parameter, so it is not used here.

=========  ======  =======  ============  ===========================================
name       unit    default  prior bounds  meaning
=========  ======  =======  ============  ===========================================
tau_drift  s/s^.5  0.0      [0, 0.2]      random-walk sd of the time gap per sqrt(s)
=========  ======  =======  ============  ===========================================
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from bayesdrive.drivers.base import DriverModel, EgoState, FilteredStart, ParamSpec, Series
from bayesdrive.drivers.execution_noise import (
    STOP_SPEED,
    acceleration_ceiling,
    censored_observation,
    implied_acceleration,
    noisy_step,
    step_logpdf,
)
from bayesdrive.drivers.extensions.compose import (
    ExtendedModel,
    base_params,
    check_base,
    extended_specs,
    state_extension,
)
from bayesdrive.drivers.extensions.inputs import ExtendedInputs, inputs_at

__all__ = ["CAUSE", "DRIFT_SPECS", "DriftState", "with_drifting_time_gap"]

CAUSE = "drifting_parameters"
DRIFT_SPECS = (
    ParamSpec(
        "tau_drift",
        "s/s^0.5",
        0.0,
        0.0,
        0.2,
        "random-walk sd of the time gap per sqrt(s)",
        grid_step=0.01,
    ),
)


# Half-width (s) of the filter's central difference in the time-gap offset (module docstring).
DIFFERENCE_STEP = 0.05


class DriftState(NamedTuple):
    """Position x (m, relative to the current step), speed v (m/s), time-gap offset (s)."""

    x: Array
    v: Array
    tau_offset: Array


@functools.cache
def with_drifting_time_gap(base: DriverModel) -> ExtendedModel:
    """``base`` whose time gap ``tau`` drifts as a random walk (module docstring)."""
    check_base(base, CAUSE)
    specs = extended_specs(base, DRIFT_SPECS)
    tau_spec = base.spec("tau")

    def rule(params, offset: Array, v: Array, inputs: ExtendedInputs) -> Array:
        own = base_params(base, params)
        tau = jnp.clip(own.tau + offset, tau_spec.lower, tau_spec.upper)
        ego = EgoState(jnp.zeros_like(v), v)
        return base.mean_acceleration(own._replace(tau=tau), ego, inputs.car_following)

    def mean_acceleration(params, state: DriftState, inputs: ExtendedInputs) -> Array:
        return rule(params, state.tau_offset, state.v, inputs)

    def transition_sample(key: Array, params, state: DriftState, inputs: ExtendedInputs):
        key_drift, key_step = jax.random.split(key)
        step = params.tau_drift * jnp.sqrt(inputs.dt)
        offset = state.tau_offset + step * jax.random.normal(key_drift, jnp.shape(state.v))
        mean_acc = rule(params, offset, state.v, inputs)
        ego = EgoState(state.x, state.v)
        sigma = base.noise_sd(base_params(base, params), ego)
        ceiling = acceleration_ceiling(state.v, inputs)
        moved = noisy_step(key_step, ego, mean_acc, sigma, inputs.dt, ceiling)
        return DriftState(moved.x, moved.v, offset)

    def transition_logpdf(
        params,
        state: DriftState,
        next_state: DriftState,
        inputs,
        *,
        may_be_censored: bool | Array = True,
    ) -> Array:
        sd = params.tau_drift * jnp.sqrt(inputs.dt)
        drift = jax.scipy.stats.norm.logpdf(next_state.tau_offset, state.tau_offset, sd)
        mean_acc = rule(params, next_state.tau_offset, state.v, inputs)
        ego = EgoState(state.x, state.v)
        sigma = base.noise_sd(base_params(base, params), ego)
        ceiling = acceleration_ceiling(state.v, inputs)
        move = step_logpdf(
            ego, next_state, mean_acc, sigma, inputs.dt, ceiling, may_be_censored=may_be_censored
        )
        return drift + move

    def lift(params, state: EgoState, inputs: ExtendedInputs) -> DriftState:
        # A simulation starts from the fitted time gap: the offset is hidden, its prior mean is 0.
        del params, inputs
        return DriftState(state.x, state.v, jnp.zeros_like(state.v))

    def initial_sample(key: Array, params, obs: EgoState) -> DriftState:
        del key, params
        return DriftState(obs.x, obs.v, jnp.zeros_like(obs.v))

    def filter_step(params, carry, xs, *, may_be_censored: bool | Array = True):
        """One step of the filter above: the offset's law (mean, variance) after the step, and
        the step's one-step predictive log density."""
        mean, var = carry
        inputs, v, next_v, dx, usable = xs
        dt = inputs.dt
        drift_var = params.tau_drift**2 * dt
        # After a gap in the data the filter restarts at the fitted time gap.
        mean = jnp.where(usable > 0, mean, 0.0)
        var = jnp.where(usable > 0, var + drift_var, 0.0)
        rule_at = rule(params, mean, v, inputs)
        above = rule(params, mean + DIFFERENCE_STEP, v, inputs)
        below = rule(params, mean - DIFFERENCE_STEP, v, inputs)
        slope = (above - below) / (2.0 * DIFFERENCE_STEP)
        state = EgoState(jnp.zeros_like(v), v)
        sigma = base.noise_sd(base_params(base, params), state)
        innovation_var = slope**2 * var + sigma**2
        ceiling = acceleration_ceiling(v, inputs)
        innovation_sd = jnp.sqrt(innovation_var)
        logp = step_logpdf(
            state,
            EgoState(dx, next_v),
            rule_at,
            innovation_sd,
            dt,
            ceiling,
            may_be_censored=may_be_censored,
        )
        gain = var * slope / innovation_var
        moving = (usable > 0) & (next_v > STOP_SPEED)
        surprise = implied_acceleration(v, dx, dt) - rule_at
        mean = jnp.where(moving, mean + gain * surprise, mean)
        # Projected onto the box, where the rule, and so J, is not flat (module docstring).
        own_tau = base_params(base, params).tau
        mean = jnp.clip(mean, tau_spec.lower - own_tau, tau_spec.upper - own_tau)
        var = jnp.where(moving, (1.0 - gain * slope) * var, var)
        return (mean, var), logp

    def offset_filter(params, steps: Any, *, may_be_censored: bool | Array = True) -> Array:
        """One-step predictive log densities of one vehicle's steps (T,), by the filter above."""
        zero = jnp.zeros_like(steps.v[0])
        _, logp = jax.lax.scan(
            lambda carry, xs: filter_step(params, carry, xs, may_be_censored=may_be_censored),
            (zero, zero),
            (steps.inputs, steps.v, steps.next_v, steps.dx, steps.mask),
        )
        return logp

    def offset_law(params, series: Series, until: Array) -> tuple[Array, Array]:
        """The offset's filtered mean and variance at step ``until`` of one vehicle's series: the
        filter above over the usable steps before it."""
        index = jnp.arange(series.v.shape[0])
        inputs = jax.vmap(lambda j: inputs_at(series, j, 0))(index)

        def step(carry, xs):
            j, *columns = xs
            # Its density is not used here (and not computed: nothing reads it).
            moved, _ = filter_step(params, carry, tuple(columns), may_be_censored=False)
            return jax.tree.map(lambda new, old: jnp.where(j < until, new, old), moved, carry), None

        zero = jnp.zeros_like(series.v[0])
        columns = (index, inputs, series.v, series.next_v, series.dx, series.mask)
        law, _ = jax.lax.scan(step, (zero, zero), columns)
        return law

    def draw_offset(key: Array, params, state: EgoState, law: tuple[Array, Array]) -> DriftState:
        del params
        mean, var = law
        # The filter's variance update may round just below 0 where the noise sd is tiny.
        offset = mean + jnp.sqrt(jnp.maximum(var, 0.0)) * jax.random.normal(key, jnp.shape(mean))
        return DriftState(state.x, state.v, offset)

    return state_extension(
        base,
        CAUSE,
        specs,
        mean_acceleration=mean_acceleration,
        transition_sample=transition_sample,
        transition_logpdf=transition_logpdf,
        censored=censored_observation,
        initial_sample=initial_sample,
        inputs_at=inputs_at,
        lift=lift,
        filter=offset_filter,
        filtered_start=FilteredStart(offset_law, draw_offset),
    )
