r"""A data-driven correction on state features: the rule-based core keeps its meaning, and a
Bayesian linear regression on a fixed basis of the driver's state fills in what the rule misses.

The base rule plus a weighted sum of three bounded features of the state,

.. math::

    a = a_{base}(v,\ s,\ v_l) + \beta_v\,\phi_v + h\,(\beta_s\,\phi_s + \beta_c\,\phi_c),

    \phi_v = \tanh\frac{v - V_0}{V_u}, \quad \phi_s = \tanh\frac{s - S_0}{S_u}, \quad
    \phi_c = \tanh\frac{v - v_l}{C_u},

where :math:`h` is 1 with a leader and 0 on free road (gap and closing speed mean nothing there).
The centres and units are fixed and data-independent (``FEATURES``): :math:`V_0` = 15 m/s and
:math:`V_u` = 10 m/s for the speed, :math:`S_0` = 20 m and :math:`S_u` = 20 m for the bumper gap,
:math:`C_u` = 2 m/s for the closing speed (positive while the driver closes in). The tanh keeps
each feature in (-1, 1), so the correction never exceeds the sum of the coefficients' sizes, and a
feature saturates instead of extrapolating where the data had no states.

Given the base parameters the mean is linear in the coefficients and the noise Gaussian, so the
coefficients' posterior is that of a linear regression of the base rule's residual acceleration on
the features, under the uniform priors below; every engine samples them with the base parameters.
All three at 0 (the defaults) is the base model. Coefficients of either sign are allowed (a
driver may brake more or less than the rule when closing in), so the criticism's score test of
this extension is two-sided in all three at once (:func:`bayesdrive.criticism.checks.score_check`);
it screens the extension on request only (:data:`~bayesdrive.drivers.extensions.DEFAULT_CAUSES`).
The applied acceleration stays within the physical limits and below the
collision-free ceiling, as in every model (:func:`~bayesdrive.drivers.execution_noise.noisy_step`).

================  =====  =======  ============  ===================================================
name              unit   default  prior bounds  meaning
================  =====  =======  ============  ===================================================
corr_speed        m/s^2  0.0      [-1, 1]       acceleration added per unit of the speed feature
corr_gap          m/s^2  0.0      [-1, 1]       acceleration added per unit of the gap feature
corr_closing      m/s^2  0.0      [-1, 1]       acceleration added per unit of the closing feature
================  =====  =======  ============  ===================================================
"""

from __future__ import annotations

import functools
from typing import NamedTuple

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

__all__ = ["CAUSE", "FEATURES", "STATE_CORRECTION_SPECS", "features", "with_state_correction"]

CAUSE = "state_correction"


class FeatureScales(NamedTuple):
    """Centres and units of the features (module docstring), fixed before any data are seen."""

    speed_centre: float = 15.0  # m/s
    speed_unit: float = 10.0  # m/s
    gap_centre: float = 20.0  # m
    gap_unit: float = 20.0  # m
    closing_unit: float = 2.0  # m/s


FEATURES = FeatureScales()


def _coefficient(name: str, feature: str) -> ParamSpec:
    return ParamSpec(
        name, "m/s^2", 0.0, -1.0, 1.0, f"acceleration added per unit of the {feature}", 0.05
    )


STATE_CORRECTION_SPECS = (
    _coefficient(
        "corr_speed",
        f"speed feature tanh((v - {FEATURES.speed_centre:g} m/s) / {FEATURES.speed_unit:g} m/s)",
    ),
    _coefficient(
        "corr_gap",
        f"gap feature tanh((s - {FEATURES.gap_centre:g} m) / {FEATURES.gap_unit:g} m), "
        "with a leader",
    ),
    _coefficient(
        "corr_closing",
        f"closing feature tanh((v - v_lead) / {FEATURES.closing_unit:g} m/s), with a leader",
    ),
)


def features(v: Array, gap: Array, lead_v: Array, has_leader: Array) -> Array:
    """The three features (speed, gap, closing) of one state, stacked on the last axis; gap and
    closing are 0 without a leader."""
    speed = jnp.tanh((v - FEATURES.speed_centre) / FEATURES.speed_unit)
    # A free road's gap is a placeholder (it may be inf): the centre puts the feature at 0.
    gap = jnp.where(has_leader > 0, gap, FEATURES.gap_centre)
    spacing = jnp.tanh((gap - FEATURES.gap_centre) / FEATURES.gap_unit)
    closing = jnp.tanh((v - lead_v) / FEATURES.closing_unit) * has_leader
    return jnp.stack([speed, spacing, closing], axis=-1)


@functools.cache
def with_state_correction(base: DriverModel) -> ExtendedModel:
    """``base`` plus the linear correction on the state features (module docstring)."""

    def mean_acceleration(params, state: EgoState, inputs: ExtendedInputs) -> Array:
        following = inputs.car_following
        rule = base.mean_acceleration(base_params(base, params), state, following)
        phi = features(state.v, following.gap, following.lead_v, following.has_leader)
        beta = jnp.stack([params.corr_speed, params.corr_gap, params.corr_closing], axis=-1)
        return rule + jnp.sum(beta * phi, axis=-1)

    check_base(base, CAUSE)
    return gaussian_extension(base, CAUSE, STATE_CORRECTION_SPECS, mean_acceleration)
