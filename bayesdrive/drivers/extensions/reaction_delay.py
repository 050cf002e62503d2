r"""Reaction delay: the driver perceives its leader as it was ``reaction_time`` seconds ago.

What the driver perceives of the leader relative to itself, the bumper gap :math:`s` and the
closing speed :math:`c = v - v_l` (read off the leader's looming), is delayed; its own speed
:math:`v`, felt and read off the speedometer, is current in the free-road and time-gap terms. With
:math:`T_r` the reaction time, the base rule is evaluated on

.. math::

    \tilde s(t) = s(t - T_r), \qquad
    \tilde v_l(t) = v(t) - \big(v(t - T_r) - v_l(t - T_r)\big),

the perceived gap and the perceived leader speed (own current speed minus the delayed closing
speed), so for the IDM

.. math::

    a(t) \sim N\Big(a_{max}\big[1 - (v/v_{des})^\delta - (d^*/\tilde s)^2\big],\ \sigma^2\Big),
    \quad d^* = d_{min} + \max\big(0,\ \tau v + v\,\tilde c / (2\sqrt{a_{max} b_{pref}})\big),

with :math:`v = v(t)` and :math:`\tilde c = v(t - T_r) - v_l(t - T_r)`. A delay of the whole rule,
the own speed included (the Human Driver Model's form), would make a driver on free road
accelerate on the speed it had a second ago, which no driver does. The delay is continuous: the
delayed values are linearly interpolated between the samples of the history window carried by
:class:`~bayesdrive.drivers.extensions.inputs.ExtendedInputs` (``lag_v``, ``lag_gap``,
``lag_lead_v``). A leader that cuts in (or appears) less than :math:`T_r` ago is perceived as it
was on entry (``lead_age``): the driver cannot perceive the new leader's past, and reacting to
the old leader, which is no longer ahead, would be no delay but a blindness; the delay then
applies to the new leader's motion from its entry on.

=============  ====  =======  ============  ===========================================
name           unit  default  prior bounds  meaning
=============  ====  =======  ============  ===========================================
reaction_time  s     0.0      [0, 1.5]      delay of the perception (0: base model)
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
        "delay of the perceived gap and closing speed",
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
    """``base`` perceiving its leader ``reaction_time`` seconds late (module docstring)."""

    def mean_acceleration(params, state: EgoState, inputs: ExtendedInputs) -> Array:
        steps = jnp.minimum(params.reaction_time / inputs.dt, inputs.lead_age)
        closing = delayed(inputs.lag_v, steps) - delayed(inputs.lag_lead_v, steps)
        perceived = CarFollowingInputs(
            gap=delayed(inputs.lag_gap, steps),
            lead_v=state.v - closing,
            has_leader=inputs.has_leader,
            dt=inputs.dt,
        )
        return base.mean_acceleration(base_params(base, params), state, perceived)

    check_base(base, CAUSE)
    return gaussian_extension(base, CAUSE, DELAY_SPECS, mean_acceleration, reads_history=True)
