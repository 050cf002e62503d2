r"""The Enhanced IDM's constant-acceleration heuristic (CAH) against over-reaction to cut-ins
(Kesting, Treiber & Helbing 2010, Phil. Trans. R. Soc. A 368:4585).

When a vehicle cuts in at a small gap, the IDM brakes hard although the situation is not critical
if the new leader is not slower. The CAH acceleration assumes both vehicles keep their current
accelerations and asks for the acceleration that just avoids a collision. With the gap :math:`s`,
speeds :math:`v, v_l` and the leader's acceleration capped at the ego's,
:math:`\tilde a_l = \min(a_l, a_{max})`:

.. math::

    a_{CAH} = \begin{cases}
      \dfrac{v^2 \tilde a_l}{v_l^2 - 2 s \tilde a_l} & v_l (v - v_l) < -2 s \tilde a_l \\[1ex]
      \tilde a_l - \dfrac{(v - v_l)^2\, \Theta(v - v_l)}{2 s} & \text{otherwise,}
    \end{cases}

and the Enhanced IDM mixes it with the base rule, with coolness :math:`c` and comfortable
deceleration :math:`b` (``b_pref``):

.. math::

    a = \begin{cases} a_{base} & a_{base} \ge a_{CAH} \\
    (1 - c)\, a_{base} + c\,\big[a_{CAH} + b \tanh\big((a_{base} - a_{CAH}) / b\big)\big]
    & \text{otherwise.} \end{cases}

Kesting et al. use c = 0.99; c = 0 is the base model. The leader's acceleration is the causal
backward difference of its observed speed (``lead_acc`` in
:class:`~bayesdrive.drivers.extensions.inputs.ExtendedInputs`). Without a leader the base rule
applies.

========  ====  =======  ============  =========================================
name      unit  default  prior bounds  meaning
========  ====  =======  ============  =========================================
coolness  --    0.0      [0, 1]        weight c of the CAH (0: the base model)
========  ====  =======  ============  =========================================
"""

from __future__ import annotations

import functools

import jax.numpy as jnp
from jax import Array

from bayesdrive.drivers.base import DriverModel, EgoState, ParamSpec
from bayesdrive.drivers.extensions.compose import (
    ExtendedModel,
    base_params,
    check_base,
    gaussian_extension,
)
from bayesdrive.drivers.extensions.inputs import ExtendedInputs
from bayesdrive.drivers.idm import MIN_GAP

__all__ = ["CAH_SPECS", "CAUSE", "cah_acceleration", "with_cut_in_heuristic"]

CAUSE = "cut_in_overreaction"
CAH_SPECS = (ParamSpec("coolness", "--", 0.0, 0.0, 1.0, "weight of the CAH", grid_step=0.05),)


def cah_acceleration(v: Array, gap: Array, lead_v: Array, lead_acc: Array, a_max: Array) -> Array:
    """The constant-acceleration heuristic (module docstring)."""
    gap = jnp.maximum(gap, MIN_GAP)
    lead_acc = jnp.minimum(lead_acc, a_max)
    # Strict inequality, as in Treiber's reference implementation: it keeps the first branch's
    # denominator positive (a stopped, non-accelerating leader falls to the second branch).
    braking_leader_stops_first = lead_v * (v - lead_v) < -2.0 * gap * lead_acc
    # Both branches are computed; the unused one's denominator must stay finite for gradients.
    denominator = jnp.where(braking_leader_stops_first, lead_v**2 - 2.0 * gap * lead_acc, 1.0)
    first = v**2 * lead_acc / denominator
    closing = jnp.maximum(v - lead_v, 0.0)
    second = lead_acc - closing**2 / (2.0 * gap)
    return jnp.where(braking_leader_stops_first, first, second)


@functools.cache
def with_cut_in_heuristic(base: DriverModel) -> ExtendedModel:
    """``base`` blended with the CAH, as the Enhanced IDM does (module docstring)."""

    def mean_acceleration(params, state: EgoState, inputs: ExtendedInputs) -> Array:
        rule = base.mean_acceleration(base_params(base, params), state, inputs.car_following)
        cah = cah_acceleration(state.v, inputs.gap, inputs.lead_v, inputs.lead_acc, params.a_max)
        comfortable = params.b_pref
        blended = (1.0 - params.coolness) * rule + params.coolness * (
            cah + comfortable * jnp.tanh((rule - cah) / comfortable)
        )
        relaxed = (inputs.has_leader > 0) & (rule < cah)
        return jnp.where(relaxed, blended, rule)

    check_base(base, CAUSE)
    return gaussian_extension(base, CAUSE, CAH_SPECS, mean_acceleration)
