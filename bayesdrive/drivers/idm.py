r"""The Intelligent Driver Model (Treiber, Hennecke & Helbing 2000) with Gaussian execution noise.

Deterministic rule, for ego speed :math:`v`, leader speed :math:`v_l`, bumper gap :math:`d` and
relative speed :math:`r = v_l - v` (a closing leader has :math:`r < 0`):

.. math::

    a_{IDM} = a_{max}\Big[1 - (v / v_{des})^{\delta} - (d_{des} / d)^2\Big], \qquad
    d_{des} = d_{min} + \max\Big(0,\; \tau v - \frac{v\, r}{2\sqrt{a_{max} b_{pref}}}\Big),

with :math:`\delta = 4`. On free road (no leader) the interaction term is absent. The dynamic part
of :math:`d_{des}` is floored at 0 as in Treiber's formulation, so a fast-receding leader never
pulls the ego closer than :math:`d_{min}`.

Stochastic IDM: :math:`a \sim \mathcal N(a_{IDM}, \sigma^2)`, the Gaussian execution noise of
:mod:`bayesdrive.drivers.execution_noise` (sigma = the paper's :math:`\sigma_{IDM}`), censored at
the vehicle's physical limits and the collision-free ceiling; that module says what the
likelihood scores.

Parameters, units, bounds of the uniform priors (the same for every engine) and defaults
(Treiber's textbook values where the paper lists them):

=========  =======  =======  ============  ==============================================
name       unit     default  prior bounds  meaning
=========  =======  =======  ============  ==============================================
v_des      m/s      30.0     [5, 45]       desired speed on free road
d_min      m        2.0      [0.5, 10]     jam distance (minimum bumper gap at standstill)
tau        s        1.0      [0.1, 4]      safe time headway
a_max      m/s^2    3.0      [0.2, 5]      maximum acceleration
b_pref     m/s^2    2.0      [0.5, 10]     comfortable (preferred) deceleration
sigma      m/s^2    0.3      [0.02, 2]     sd of the Gaussian execution noise
=========  =======  =======  ============  ==============================================
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array

from bayesdrive.drivers.base import CarFollowingInputs, EgoState, ParamSpec
from bayesdrive.drivers.execution_noise import EXECUTION_NOISE_SD, execution_noise_model

__all__ = ["DELTA", "IDM", "MIN_GAP", "IDMParams", "equilibrium_gap", "idm_acceleration"]

# An integer, so powers of it compile to multiplications: a float exponent is exp(4 log x),
# which made the likelihood several times slower.
DELTA = 4
# The interaction term diverges at zero gap; the simulator counts a collision long before.
MIN_GAP = 0.1

# pf grid steps: v_des and sigma are the paper's; the others are about 1-5% of the prior width,
# fine against what one 20 s trajectory can resolve.
IDM_SPECS = (
    ParamSpec("v_des", "m/s", 30.0, 5.0, 45.0, "desired speed", grid_step=0.5, desired_speed=True),
    ParamSpec("d_min", "m", 2.0, 0.5, 10.0, "jam distance", grid_step=0.5),
    ParamSpec("tau", "s", 1.0, 0.1, 4.0, "safe time headway", grid_step=0.1),
    ParamSpec("a_max", "m/s^2", 3.0, 0.2, 5.0, "maximum acceleration", grid_step=0.1),
    ParamSpec("b_pref", "m/s^2", 2.0, 0.5, 10.0, "comfortable deceleration", grid_step=0.5),
    EXECUTION_NOISE_SD,
)


class IDMParams(NamedTuple):
    r"""Stochastic IDM: :math:`a \sim N(a_{IDM}(v, d, r), \sigma^2)` (module docstring for the rule).

    v_des (m/s), d_min (m), tau (s), a_max (m/s^2), b_pref (m/s^2), sigma (m/s^2).
    """

    v_des: Array
    d_min: Array
    tau: Array
    a_max: Array
    b_pref: Array
    sigma: Array


def idm_acceleration(params, v: Array, gap: Array, lead_v: Array, has_leader: Array) -> Array:
    """The deterministic IDM acceleration; ``params`` needs v_des, d_min, tau, a_max, b_pref."""
    free = 1.0 - (v / params.v_des) ** DELTA
    closing = v - lead_v  # = -r: positive while the ego gains on its leader
    dynamic = v * params.tau + v * closing / (2.0 * jnp.sqrt(params.a_max * params.b_pref))
    desired_gap = params.d_min + jnp.maximum(0.0, dynamic)
    # A safe gap of 1 where there is no leader keeps gradients finite; the term is masked anyway.
    safe_gap = jnp.maximum(jnp.where(has_leader > 0, gap, 1.0), MIN_GAP)
    interaction = jnp.where(has_leader > 0, (desired_gap / safe_gap) ** 2, 0.0)
    return params.a_max * (free - interaction)


def equilibrium_gap(params, v: Array) -> Array:
    """The bumper gap at which the IDM holds speed ``v`` behind a leader at the same speed:
    d_e = (d_min + tau v) / sqrt(1 - (v / v_des)^delta), for 0 <= v < v_des."""
    return (params.d_min + params.tau * v) / jnp.sqrt(1.0 - (v / params.v_des) ** DELTA)


def _mean_acceleration(params: IDMParams, state: EgoState, inputs: CarFollowingInputs) -> Array:
    return idm_acceleration(params, state.v, inputs.gap, inputs.lead_v, inputs.has_leader)


IDM = execution_noise_model("idm", IDMParams, IDM_SPECS, _mean_acceleration)
