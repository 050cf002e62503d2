"""The Gipps (1981) car-following model, reaction time = one step, Gaussian execution noise.

A second base model beside the IDM: it needs only its rule, its parameter specs and
:func:`~bayesdrive.drivers.execution_noise.execution_noise_model`; every engine and the simulator take it
unchanged. Bounds of the uniform priors are wide around Gipps' own simulation values (a 1.7,
b 3.4, b-hat 3.2 m/s^2, V 20 m/s, effective size 6.5 m = a car of 4.5 m + 2 m margin).

**For NUTS.** The mean acceleration is continuous in every parameter, but min() makes its
gradient piecewise: on a step where the free branch wins, the safe-branch parameters (b_max,
b_lead, d_min) get no gradient from it, and the other way round, so the log density has kinks
where a step changes branch. Measured (``reports/gipps_nuts.md``, first six NGSIM I-80 followers,
engine defaults, 1000 draws): no divergence on three vehicles, 72-101 on the other three, where
the IDM had 0-1. The kink does not explain them all: vehicle 11 (101) has one step of 174 whose
branch differs between posterior draws, its divergent draws sit among the others, far from the
safe-speed floor, and its safe-branch parameters fill their prior boxes. Prefer ``smc`` for Gipps.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array

from bayesdrive.drivers.base import CarFollowingInputs, EgoState, ParamSpec
from bayesdrive.drivers.execution_noise import EXECUTION_NOISE_SD, execution_noise_model

__all__ = ["GIPPS", "GippsParams", "gipps_acceleration"]

# Keeps sqrt's gradient finite where the safe-speed radicand is floored (a gap already too short).
RADICAND_FLOOR = 1e-6

GIPPS_SPECS = (
    ParamSpec(
        "v_des", "m/s", 20.0, 5.0, 45.0, "desired speed V", grid_step=0.5, desired_speed=True
    ),
    ParamSpec("a_max", "m/s^2", 1.7, 0.2, 5.0, "maximum acceleration a", grid_step=0.1),
    ParamSpec("b_max", "m/s^2", 3.4, 0.5, 10.0, "most severe braking b (as > 0)", grid_step=0.5),
    ParamSpec("b_lead", "m/s^2", 3.2, 0.5, 10.0, "leader's braking as estimated", grid_step=0.5),
    ParamSpec("d_min", "m", 2.0, 0.5, 10.0, "margin s - L kept at standstill", grid_step=0.5),
    EXECUTION_NOISE_SD,
)


class GippsParams(NamedTuple):
    r"""Gipps (1981) with reaction time :math:`\tau = \Delta t` and braking written positive.

    For speed :math:`v`, leader speed :math:`v_l` and bumper gap :math:`g`, the speed one step on is

    .. math::

        v_{free} = v + 2.5\, a_{max} \tau (1 - v/v_{des}) \sqrt{0.025 + v/v_{des}}, \\
        v_{safe} = -b_{max}\tau + \sqrt{b_{max}^2\tau^2
            + b_{max}\big(2(g - d_{min}) - v\tau + v_l^2/b_{lead}\big)}, \\
        v^* = \max\big(0, \min(v_{free}, v_{safe})\big)

    (:math:`v^* = v_{free}` on free road), and the acceleration is
    :math:`a \sim N((v^* - v)/\tau, \sigma^2)`, stepped and scored like the IDM's
    (:mod:`bayesdrive.drivers.execution_noise`).
    Gipps' effective size :math:`s` of the leader is its length plus :math:`d_{min}`.

    v_des (m/s), a_max, b_max, b_lead, sigma (m/s^2), d_min (m).
    """

    v_des: Array
    a_max: Array
    b_max: Array
    b_lead: Array
    d_min: Array
    sigma: Array


def gipps_acceleration(params: GippsParams, state: EgoState, inputs: CarFollowingInputs) -> Array:
    """The deterministic Gipps acceleration (:class:`GippsParams`), reaction time = ``inputs.dt``."""
    v, tau, b = state.v, inputs.dt, params.b_max
    ratio = v / params.v_des
    free = v + 2.5 * params.a_max * tau * (1.0 - ratio) * jnp.sqrt(0.025 + ratio)
    # Without a leader the gap may be NaN; any finite value keeps the masked branch's gradient clean.
    gap = jnp.where(inputs.has_leader > 0, inputs.gap, 1.0)
    braking = 2.0 * (gap - params.d_min) - v * tau + inputs.lead_v**2 / params.b_lead
    safe = -b * tau + jnp.sqrt(jnp.maximum((b * tau) ** 2 + b * braking, RADICAND_FLOOR))
    target = jnp.where(inputs.has_leader > 0, jnp.minimum(free, safe), free)
    return (jnp.maximum(target, 0.0) - v) / tau


GIPPS = execution_noise_model("gipps", GippsParams, GIPPS_SPECS, gipps_acceleration)
