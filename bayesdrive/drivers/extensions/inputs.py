r"""Extended inputs: what the model extensions read beyond the current gap and leader speed.

The base models see one step's :class:`~bayesdrive.drivers.base.CarFollowingInputs`. The extensions
need more, and all of it is read from the one series (:class:`~bayesdrive.drivers.base.Series`,
the device form of :class:`~bayesdrive.data.views.FollowerArrays`), or, in a simulation, from a
buffer of it that the simulation writes into, so data scoring and rollouts never disagree about
what the driver sees:

* a short **history window** of the ego's speed, its gap and its leader's speed, ``lag_k`` = the
  value k steps ago (k = 0 is now, k = 1..K the past, K = ``ceil(HISTORY_SECONDS / dt)``), for
  the reaction delay, which interpolates between samples for a continuous delay;
* the **second vehicle ahead** and the leader's **acceleration** (the series' ``ahead`` part).

**Which steps are scored.** A model that reads its past is scored only on steps whose K steps
before are usable too (:func:`~bayesdrive.inference.core.likelihood.step_inputs`); a model comparison
scores every model on the same such steps (:func:`~bayesdrive.data.views.scored_series`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array

from bayesdrive.data.views import HISTORY_SECONDS, history_steps
from bayesdrive.drivers.base import Series, car_following_at, car_following_part

__all__ = ["HISTORY_SECONDS", "ExtendedInputs", "history_steps", "inputs_at"]


class ExtendedInputs(NamedTuple):
    """One step's inputs for the extensions; the first four fields are the base model's inputs.

    gap, lead_v, has_leader, dt: as in :class:`~bayesdrive.drivers.base.CarFollowingInputs`.
    lead_acc: the leader's acceleration, backward difference of its observed speed (m/s^2).
    gap2: bumper gap to the leader plus the leader's bumper gap to its own leader (m).
    lead2_v: speed of the second vehicle ahead (m/s).
    has_leader2: 1.0 when a second vehicle ahead is known, else 0.0.
    lead_age: steps the current leader has been the leader (0 on the step it cuts in).
    lag_v, lag_gap, lag_lead_v: (K + 1,) ego speed, gap and leader speed k steps ago (k = 0: now).
    """

    gap: Array
    lead_v: Array
    has_leader: Array
    dt: Array
    lead_acc: Array
    gap2: Array
    lead2_v: Array
    has_leader2: Array
    lead_age: Array
    lag_v: Array
    lag_gap: Array
    lag_lead_v: Array

    car_following = property(car_following_part)


def inputs_at(series: Series, j: Array, history: int) -> ExtendedInputs:
    """The :class:`ExtendedInputs` of step ``j`` of one vehicle (``series`` fields have shape (S,)).

    Lags reaching before the first sample repeat the first sample; such steps are never scored
    (see the module docstring), so the repetition only keeps the arrays finite.
    """
    if series.ahead is None:
        raise ValueError(
            "the model extensions read the vehicle ahead of the leader; these data have no such "
            "part (build them from trajectories with data.views.follower_arrays)"
        )
    lags = jnp.maximum(j - jnp.arange(history + 1), 0)
    ahead = series.ahead
    return ExtendedInputs(
        **car_following_at(series, j, history)._asdict(),
        **{name: values[j] for name, values in ahead._asdict().items()},
        lag_v=series.v[lags],
        lag_gap=series.gap[lags],
        lag_lead_v=series.lead_v[lags],
    )
