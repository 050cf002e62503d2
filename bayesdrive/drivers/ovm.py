r"""The Optimal Velocity Model (Bando, Hasebe, Nakayama, Shibata & Sugiyama, Phys. Rev. E 51, 1035,
1995) with Gaussian execution noise.

Bando et al. write the car-following rule as :math:`\ddot x_n = a\,[V(\Delta x_n) - \dot x_n]`: the
driver relaxes its speed at rate :math:`a` (the sensitivity, 1/s) towards an optimal velocity that
depends on the distance ahead alone, and in the paper's dimensionless units
:math:`V(b) = \tanh(b - 2) + \tanh 2`. In physical units, with the bumper gap :math:`s` measured in
units of a length :math:`s_c` and speeds in units of :math:`v_{max}/2`, that is

.. math::

    a_{OVM} = \kappa\,\big[V(s) - v\big], \qquad
    V(s) = \frac{v_{max}}{2}\Big[\tanh\Big(\frac{s}{s_c} - 2\Big) + \tanh 2\Big],

so :math:`V(0) = 0`, :math:`V` rises fastest at :math:`s = 2 s_c` and tends to
:math:`V(\infty) = v_{max}(1 + \tanh 2)/2` on free road (no leader), which is the optimal velocity
used there. The leader's speed does not enter (the model's defining simplification). The noise
is the shared Gaussian execution noise (:mod:`bayesdrive.drivers.execution_noise`):
:math:`a \sim \mathcal N(a_{OVM}, \sigma^2)`.

Parameters, units, bounds of the uniform priors (the same for every engine) and defaults:

=====  =======  =======  ============  ====================================================
name   unit     default  prior bounds  meaning
=====  =======  =======  ============  ====================================================
kappa  1/s      1.0      [0.1, 4]      sensitivity: rate of relaxation to the optimal velocity
v_max  m/s      30.0     [5, 45]       optimal velocity scale (free road: 0.982 v_max)
s_c    m        10.0     [1, 40]       gap scale of the optimal velocity function
sigma  m/s^2    0.3      [0.02, 2]     sd of the Gaussian execution noise
=====  =======  =======  ============  ====================================================

``v_max`` sets the free-road speed, so it is marked as the desired speed.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array

from bayesdrive.drivers.base import CarFollowingInputs, EgoState, ParamSpec
from bayesdrive.drivers.execution_noise import EXECUTION_NOISE_SD, execution_noise_model

__all__ = ["OVM", "OVMParams", "optimal_velocity", "ovm_acceleration"]

# Bando et al.'s offset: the optimal velocity rises fastest at a gap of 2 s_c.
INFLECTION = 2.0

OVM_SPECS = (
    ParamSpec("kappa", "1/s", 1.0, 0.1, 4.0, "sensitivity", grid_step=0.05),
    ParamSpec(
        "v_max", "m/s", 30.0, 5.0, 45.0, "optimal velocity scale", grid_step=0.5, desired_speed=True
    ),
    ParamSpec("s_c", "m", 10.0, 1.0, 40.0, "gap scale of the optimal velocity", grid_step=0.5),
    EXECUTION_NOISE_SD,
)


class OVMParams(NamedTuple):
    r"""Stochastic OVM: :math:`a \sim N(\kappa[V(s) - v], \sigma^2)` (module docstring).

    kappa (1/s), v_max (m/s), s_c (m), sigma (m/s^2).
    """

    kappa: Array
    v_max: Array
    s_c: Array
    sigma: Array


def optimal_velocity(params: OVMParams, gap: Array) -> Array:
    """V(s) = v_max / 2 [tanh(s / s_c - 2) + tanh 2] (module docstring)."""
    return 0.5 * params.v_max * (jnp.tanh(gap / params.s_c - INFLECTION) + jnp.tanh(INFLECTION))


def ovm_acceleration(params: OVMParams, state: EgoState, inputs: CarFollowingInputs) -> Array:
    """The deterministic OVM acceleration; on free road the optimal velocity is V(infinity)."""
    # Without a leader the gap may be NaN; any finite value keeps the masked branch's gradient clean.
    gap = jnp.where(inputs.has_leader > 0, inputs.gap, 1.0)
    free = 0.5 * params.v_max * (1.0 + jnp.tanh(INFLECTION))
    target = jnp.where(inputs.has_leader > 0, optimal_velocity(params, gap), free)
    return params.kappa * (target - state.v)


OVM = execution_noise_model("ovm", OVMParams, OVM_SPECS, ovm_acceleration)
