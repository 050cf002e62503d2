r"""Reaction delay: the driver responds to the situation as it was ``reaction_time`` seconds ago.

The base rule is evaluated on delayed perceptions (as in Treiber, Kesting & Helbing's Human Driver
Model, 2006): with :math:`T_r` the reaction time,

.. math::

    a(t) \sim N\big(a_{base}(v(t - T_r),\ s(t - T_r),\ v_l(t - T_r)),\ \sigma^2\big),

while the kinematics use the current speed. The delay is continuous: the delayed values are
linearly interpolated between the samples of the history window carried by
:class:`~bayesdrive.drivers.extensions.inputs.ExtendedInputs` (``lag_v``, ``lag_gap``,
``lag_lead_v``). A leader that cuts in (or appears) less than :math:`T_r` ago is perceived as it
was on entry (``lead_age``): the driver cannot perceive the new leader's past, and reacting to
the old leader, which is no longer ahead, would be no delay but a blindness; the delay then
applies to the new leader's motion from its entry on.

=============  ====  =======  ============  ===========================================
name           unit  default  prior bounds  meaning
=============  ====  =======  ============  ===========================================
reaction_time  s     0.0      [0, 1.5]      delay of the response (0: the base model)
=============  ====  =======  ============  ===========================================

The upper bound is :data:`~bayesdrive.drivers.extensions.inputs.HISTORY_SECONDS`, the length of
the history window.
"""

from __future__ import annotations

import functools

import jax.numpy as jnp
from jax import Array

from bayesdrive.drivers.base import CarFollowingInputs, DriverModel, EgoState, ParamSpec
from bayesdrive.drivers.extensions.compose import (
    ExtendedModel,
    base_params,
    check_base,
    gaussian_extension,
)
from bayesdrive.drivers.extensions.inputs import HISTORY_SECONDS, ExtendedInputs

__all__ = ["CAUSE", "DELAY_SPECS", "delayed", "with_reaction_delay"]

CAUSE = "reaction_delay"
DELAY_SPECS = (
    ParamSpec(
        "reaction_time",
        "s",
        0.0,
        0.0,
        HISTORY_SECONDS,
        "delay of the response to the situation",
        grid_step=0.1,
    ),
)


def delayed(lagged: Array, delay_steps: Array) -> Array:
    """Linear interpolation of ``lagged`` (index k = k steps ago) at a fractional lag."""
    last = lagged.shape[-1] - 1
    lower = jnp.clip(jnp.floor(delay_steps), 0, last - 1).astype(jnp.int32)
    # In [0, 1] for delays inside the window; not clipped, so the slope at zero delay is exact.
    fraction = delay_steps - lower
    below = jnp.take(lagged, lower, axis=-1)
    above = jnp.take(lagged, lower + 1, axis=-1)
    return (1.0 - fraction) * below + fraction * above


@functools.cache
def with_reaction_delay(base: DriverModel) -> ExtendedModel:
    """``base`` responding to its inputs ``reaction_time`` seconds late (module docstring)."""

    def mean_acceleration(params, state: EgoState, inputs: ExtendedInputs) -> Array:
        steps = params.reaction_time / inputs.dt
        leader_steps = jnp.minimum(steps, inputs.lead_age)
        perceived = CarFollowingInputs(
            gap=delayed(inputs.lag_gap, leader_steps),
            lead_v=delayed(inputs.lag_lead_v, leader_steps),
            has_leader=inputs.has_leader,
            dt=inputs.dt,
        )
        past_self = EgoState(x=state.x, v=delayed(inputs.lag_v, steps))
        return base.mean_acceleration(base_params(base, params), past_self, perceived)

    check_base(base, CAUSE)
    return gaussian_extension(base, CAUSE, DELAY_SPECS, mean_acceleration, reads_history=True)
