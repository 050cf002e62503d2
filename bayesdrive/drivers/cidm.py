r"""The Cooperative IDM (Bouton et al. 2019), with several merge-lane vehicles as in the paper.

The ego drives on the main lane towards a merge point; up to K vehicles approach the same point on
the merge lane. Distances are measured from each vehicle's *front bumper* to the merge point along
its own lane (m, positive before the point, negative once past it); speeds in m/s, lengths in m.

**Time to merge** by constant velocity, for the ego and every merge-lane vehicle k:

.. math::

    TTM = d / v \quad (v > 0), \qquad TTM = \infty \quad (v = 0).

A merge-lane vehicle is a *candidate* when it is present and has not passed the merge point
(:math:`d_k \ge 0`). The ego considers the one candidate :math:`k^*` whose TTM is closest to its
own, :math:`\arg\min_k |TTM_k - TTM_{ego}|` (for a stopped ego, :math:`TTM_{ego} = \infty`, the
limit of that rule: the candidate with the largest TTM). It **yields** when, with cooperation
:math:`c \in [0, 1]`,

.. math::

    d_{ego} \ge 0, \quad TTM_{k^*} < TTM_{ego}, \quad TTM_{k^*} < c\, TTM_{ego},

i.e. the ego has not passed the merge point and the merging vehicle arrives first, early enough.
So :math:`c = 0` never yields (no TTM of a candidate is negative; for a stopped ego
:math:`0 \cdot \infty` is undefined and compares false) and :math:`c = 1` yields to every vehicle
that arrives first. The paper prints the inequality the other way round
(:math:`TTM_{ego} < c\,TTM_{other}`, under which a larger c would yield *less*); its code does what
is written here, and so do we.

Yielding means following the IDM towards the merging vehicle projected onto the ego's lane at the
same distance to the merge point, and never accelerating harder than the IDM towards the real
leader:

.. math::

    a_{CIDM} = \min\big(a_{IDM}(v, d_{ego} - d_{k^*} - L_{k^*}, v_{k^*}),\ a_{IDM}(v, d, v_l)\big)
    \ \text{if yielding, else}\ a_{IDM}(v, d, v_l).

The projected gap can be small or negative (the merging vehicle is beside or behind the ego but
faster); the IDM's gap floor then makes the ego brake hard, which is the intended yield.

Stochastic exactly like the IDM: :math:`a \sim N(a_{CIDM}, \sigma^2)`, the same
:func:`~bayesdrive.drivers.execution_noise.noisy_step` and the same exact one-step density
:func:`~bayesdrive.drivers.execution_noise.step_logpdf` (see
:mod:`bayesdrive.drivers.execution_noise`).

Parameters: the IDM's six (same units, bounds, defaults; see :mod:`bayesdrive.drivers.idm`) plus

=====  ====  =======  ============  =====================================================
name   unit  default  prior bounds  meaning
=====  ====  =======  ============  =====================================================
c      --    0.5      [0, 1]        cooperation: yield when TTM_other < c * TTM_ego
=====  ====  =======  ============  =====================================================

**Not differentiable in c.** The yield decision is a hard threshold in c, so the likelihood is
piecewise constant in c (gradient zero almost everywhere, jumps at the thresholds). Gradients with
respect to the IDM parameters are exact. Samplers that need gradients (NUTS) must treat c apart,
e.g. by smoothing the threshold (a sigmoid in :math:`c\,TTM_{ego} - TTM_{other}` with a stated
temperature) or by marginalising/Gibbs-updating c; particle filters and other derivative-free
engines can use the model as is.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array

from bayesdrive.drivers.base import (
    EgoState,
    ParamSpec,
    Series,
    car_following_part,
    params_type,
)
from bayesdrive.drivers.execution_noise import execution_noise_model
from bayesdrive.drivers.idm import IDM, idm_acceleration

__all__ = [
    "CIDM",
    "MERGE_SCENE",
    "CIDMParams",
    "MergeInputs",
    "cidm_acceleration",
    "merge_inputs_at",
    "time_to_merge",
    "yield_target",
]

CIDM_SPECS = (
    *IDM.specs,
    ParamSpec(
        "c", "--", 0.5, 0.0, 1.0, "cooperation: yield when TTM_other < c * TTM_ego", grid_step=0.1
    ),
)


# Cooperative IDM: the IDM's parameters plus cooperation c in [0, 1] (module docstring).
CIDMParams = params_type("CIDMParams", CIDM_SPECS)
CIDMParams.__module__ = __name__  # pickled by reference, as a class statement here would be


class MergeInputs(NamedTuple):
    """The car-following inputs (same first four fields) plus the merge scene at one step.

    gap, lead_v, has_leader, dt: as in :class:`~bayesdrive.drivers.base.CarFollowingInputs`.
    ego_to_merge: the ego's front-bumper distance to the merge point (m; negative once past it).
    merge_to_merge: (K,) each merge-lane vehicle's front-bumper distance to the merge point (m).
    merge_v: (K,) their speeds (m/s).
    merge_length: (K,) their lengths (m).
    merge_present: (K,) 1.0 for a real vehicle, 0.0 for a padded slot (padded slots hold finite
        values, so gradients stay finite).
    """

    gap: Array
    lead_v: Array
    has_leader: Array
    dt: Array
    ego_to_merge: Array
    merge_to_merge: Array
    merge_v: Array
    merge_length: Array
    merge_present: Array

    car_following = property(car_following_part)


def time_to_merge(distance: Array, speed: Array) -> Array:
    """Constant-velocity time to reach the merge point: distance / speed, +inf at zero speed."""
    moving = speed > 0
    # Divide by a safe speed so the unused branch never produces inf * 0 = NaN in gradients.
    return jnp.where(moving, distance / jnp.where(moving, speed, 1.0), jnp.inf)


def yield_target(c: Array, v: Array, inputs: MergeInputs) -> tuple[Array, Array]:
    """Whether the ego yields, and to which merge-lane slot (an index in 0..K-1).

    The decision is a hard threshold in ``c`` (module docstring); the index is only meaningful
    where the first output is true.
    """
    ttm_ego = time_to_merge(inputs.ego_to_merge, v)
    ttm_other = time_to_merge(inputs.merge_to_merge, inputs.merge_v)
    candidate = (inputs.merge_present > 0) & (inputs.merge_to_merge >= 0)
    # |TTM_k - TTM_ego|, and its limit -TTM_k for a stopped ego (inf - inf would be NaN).
    closeness = jnp.where(jnp.isfinite(ttm_ego), jnp.abs(ttm_other - ttm_ego), -ttm_other)
    closeness = jnp.where(candidate, closeness, jnp.inf)
    chosen = jnp.argmin(closeness)
    ttm_chosen = ttm_other[chosen]
    yields = (
        candidate[chosen]
        & (inputs.ego_to_merge >= 0)
        & (ttm_chosen < ttm_ego)
        # c = 0 never passes: candidates have TTM >= 0, and 0 * inf = NaN compares false.
        & (ttm_chosen < c * ttm_ego)
    )
    return yields, chosen


def cidm_acceleration(params, v: Array, inputs: MergeInputs) -> Array:
    """The deterministic Cooperative-IDM acceleration (module docstring); needs the IDM fields + c."""
    if not isinstance(inputs, MergeInputs):
        raise TypeError(
            f"the Cooperative IDM needs MergeInputs (car-following inputs plus the merge scene), "
            f"got {type(inputs).__name__}"
        )
    follow_leader = idm_acceleration(params, v, inputs.gap, inputs.lead_v, inputs.has_leader)
    yields, k = yield_target(params.c, v, inputs)
    projected_gap = inputs.ego_to_merge - inputs.merge_to_merge[k] - inputs.merge_length[k]
    follow_merger = idm_acceleration(params, v, projected_gap, inputs.merge_v[k], 1.0)
    return jnp.where(yields, jnp.minimum(follow_merger, follow_leader), follow_leader)


def _mean_acceleration(params: CIDMParams, state: EgoState, inputs: MergeInputs) -> Array:
    return cidm_acceleration(params, state.v, inputs)


def merge_inputs_at(series: Series, j: Array, history: int) -> MergeInputs:
    """Step ``j``'s car-following inputs and merge scene (the series must carry one)."""
    del history
    if series.merge is None:
        raise ValueError(
            "the Cooperative IDM reads the merge scene, and these data have none: fit it to "
            "merge episodes (simulation.scenarios.merge_follower_arrays)"
        )
    return MergeInputs(
        series.gap[j],
        series.lead_v[j],
        series.has_leader[j],
        series.dt[j],
        *(part[j] for part in series.merge),
    )


# The simulator must put it in merge scenes; extensions that read car following alone refuse it.
MERGE_SCENE = "merge"

CIDM = execution_noise_model(
    "cidm",
    CIDMParams,
    CIDM_SPECS,
    _mean_acceleration,
    inputs_at=merge_inputs_at,
    scene=MERGE_SCENE,
)
