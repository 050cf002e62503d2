r"""Anticipation of the second vehicle ahead (multi-anticipation, after Treiber, Kesting & Helbing's
Human Driver Model, 2006).

The driver blends the base rule towards its leader with the base rule towards the vehicle two
ahead, seen at half the sum of the two bumper gaps:

.. math::

    a = (1 - w)\, a_{base}(v,\ s_1,\ v_1) + w\, a_{base}\big(v,\ \tfrac12 (s_1 + s_{12}),\ v_2\big),

where :math:`s_1` is the gap to the leader, :math:`s_{12}` the leader's gap to its own leader and
:math:`v_2` that vehicle's speed (``gap2`` :math:`= s_1 + s_{12}` and ``lead2_v`` in
:class:`~bayesdrive.drivers.extensions.inputs.ExtendedInputs`). For the IDM this is exactly the
multi-anticipative interaction term :math:`(1-w)(d^*_1/s_1)^2 + w(2 d^*_2/(s_1+s_{12}))^2`: in a
homogeneous platoon (equal gaps and speeds) both terms agree, so the steady state is the base
model's for every w, and only the reaction to what happens two vehicles ahead changes. Without a
known second vehicle ahead the base rule applies.

============  ====  =======  ============  ==============================================
name          unit  default  prior bounds  meaning
============  ====  =======  ============  ==============================================
anticipation  --    0.0      [0, 1]        weight w of the second vehicle ahead
============  ====  =======  ============  ==============================================
"""

from __future__ import annotations

import functools

from jax import Array

from bayesdrive.drivers.base import CarFollowingInputs, DriverModel, EgoState, ParamSpec
from bayesdrive.drivers.extensions.compose import (
    ExtendedModel,
    base_params,
    check_base,
    gaussian_extension,
)
from bayesdrive.drivers.extensions.inputs import ExtendedInputs

__all__ = ["ANTICIPATION_SPECS", "CAUSE", "with_second_leader_anticipation"]

CAUSE = "second_leader_anticipation"
ANTICIPATION_SPECS = (
    ParamSpec(
        "anticipation", "--", 0.0, 0.0, 1.0, "weight of the second vehicle ahead", grid_step=0.05
    ),
)


@functools.cache
def with_second_leader_anticipation(base: DriverModel) -> ExtendedModel:
    """``base`` also reacting to the second vehicle ahead with weight ``anticipation``."""

    def mean_acceleration(params, state: EgoState, inputs: ExtendedInputs) -> Array:
        own = base_params(base, params)
        to_leader = base.mean_acceleration(own, state, inputs.car_following)
        second = CarFollowingInputs(
            0.5 * inputs.gap2, inputs.lead2_v, inputs.has_leader2, inputs.dt
        )
        to_second = base.mean_acceleration(own, state, second)
        weight = params.anticipation * inputs.has_leader2 * inputs.has_leader
        return (1.0 - weight) * to_leader + weight * to_second

    check_base(base, CAUSE)
    return gaussian_extension(base, CAUSE, ANTICIPATION_SPECS, mean_acceleration)
