r"""Anticipation of the leader's acceleration: the driver reacts to what its leader is doing now,
not only to the gap and closing speed it has already produced.

The base rule plus a weight of the leader's acceleration,

.. math::

    a = a_{base}(v,\ s,\ v_l) + w\, \operatorname{clip}(a_l,\ -b_{phys},\ a_{phys}),

where :math:`a_l` is the causal backward difference of the leader's observed speed over the last
step (``lead_acc`` in :class:`~bayesdrive.drivers.extensions.inputs.ExtendedInputs`), clipped to
the range a car can physically reach, :math:`[-b_{phys}, a_{phys}]` = [-``MAX_BRAKING``,
``MAX_ACCELERATION``] = [-9, 6] m/s^2 (:mod:`bayesdrive.drivers.execution_noise`): a backward
difference of recorded speeds can leave it where a speed was misread, and one such step would
otherwise set the mean. Adaptive cruise control models read the leader's acceleration the same
way (Kesting, Treiber & Helbing's ACC model takes it into its constant-acceleration heuristic,
:mod:`.cut_in`); here it enters linearly, so w is the share of the leader's acceleration the
driver copies. In steady following the leader does not accelerate and the steady state is the
base model's for every w. Without a leader the base rule applies. The applied acceleration stays
within the physical limits and below the collision-free ceiling, as in every model
(:func:`~bayesdrive.drivers.execution_noise.noisy_step`).

The prior is uniform on [0, 1]: 0 (the default) is the base model, 1 copies the leader's whole
acceleration on top of the base rule's own response; negative weights (a driver acting against
its leader's acceleration) are left out, so the criticism's one-sided score test applies.

=================  ====  =======  ============  ==================================================
name               unit  default  prior bounds  meaning
=================  ====  =======  ============  ==================================================
leader_acc_weight  --    0.0      [0, 1]        weight w of the leader's acceleration (0: base)
=================  ====  =======  ============  ==================================================
"""

from __future__ import annotations

import functools

import jax.numpy as jnp
from jax import Array

from bayesdrive.drivers.base import DriverModel, EgoState, ParamSpec
from bayesdrive.drivers.execution_noise import MAX_ACCELERATION, MAX_BRAKING
from bayesdrive.drivers.extensions.compose import (
    ExtendedModel,
    base_params,
    check_base,
    gaussian_extension,
)
from bayesdrive.drivers.extensions.inputs import ExtendedInputs

__all__ = ["CAUSE", "LEADER_ACCELERATION_SPECS", "with_leader_acceleration_anticipation"]

CAUSE = "leader_acceleration_anticipation"
LEADER_ACCELERATION_SPECS = (
    ParamSpec(
        "leader_acc_weight",
        "--",
        0.0,
        0.0,
        1.0,
        "weight of the leader's acceleration added to the base rule",
        grid_step=0.05,
    ),
)


@functools.cache
def with_leader_acceleration_anticipation(base: DriverModel) -> ExtendedModel:
    """``base`` plus ``leader_acc_weight`` times its leader's acceleration (module docstring)."""

    def mean_acceleration(params, state: EgoState, inputs: ExtendedInputs) -> Array:
        rule = base.mean_acceleration(base_params(base, params), state, inputs.car_following)
        leader_acc = jnp.clip(inputs.lead_acc, -MAX_BRAKING, MAX_ACCELERATION)
        return rule + params.leader_acc_weight * inputs.has_leader * leader_acc

    check_base(base, CAUSE)
    return gaussian_extension(base, CAUSE, LEADER_ACCELERATION_SPECS, mean_acceleration)
