r"""Extended inputs: what the model extensions need beyond the current gap and leader speed.

The base models see one step's :class:`~bayesdrive.drivers.base.CarFollowingInputs`. The extensions
need more, and all of it is read from observed data (or, in a simulation, from the simulated ego
and the replayed vehicles ahead):

* a short **history window** of the ego's speed, its gap and its leader's speed, ``lag_k`` = the
  value k steps ago (k = 0 is now, k = 1..K the past, K = ``ceil(HISTORY_SECONDS / dt)``), for
  the reaction delay, which interpolates between samples for a continuous delay;
* the ego's **previous position increment** ``prev_dx`` (x[t] - x[t-1]), from which the previous
  step's acceleration residual is recovered exactly (autocorrelated noise);
* the **second vehicle ahead**: ``gap2`` = the sum of the two bumper gaps (ego to leader, leader to
  its leader; the leader's length left out) and its speed ``lead2_v``;
* the leader's **acceleration** ``lead_acc``, a backward difference of its observed speed (causal:
  it uses only samples up to now), for the constant-acceleration heuristic.

Data come in as :class:`ExtendedSeries`: per-vehicle, per-sample arrays padded to a common length,
where step ``j`` scores the transition from sample j to j+1 (as in
:class:`~bayesdrive.data.views.FollowerArrays`, whose arrays and mask it reuses). :func:`inputs_at`
reads one step's :class:`ExtendedInputs` from such per-vehicle arrays; the same function serves data
scoring (vmapped over steps) and closed-loop rollouts (inside a scan, on a buffer the simulation
writes into), so the two never disagree about what the driver sees.

**Which steps are scored.** A step is scored only if every one of the K steps before it is a
usable car-following step too, so every model, with or without history, is scored on exactly the
same steps (the comparison of models is then fair). The first ``HISTORY_SECONDS`` of every vehicle
and of every stretch after a gap in the data are therefore left out; :func:`extended_series`
logs how many steps that removes.
"""

from __future__ import annotations

import logging
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from jax import Array

from bayesdrive.data.errors import DataError
from bayesdrive.data.trajectories import Trajectories
from bayesdrive.data.views import follower_arrays
from bayesdrive.drivers.base import CarFollowingInputs

__all__ = [
    "HISTORY_SECONDS",
    "ExtendedInputs",
    "ExtendedSeries",
    "VehicleSeries",
    "extended_series",
    "history_steps",
    "inputs_at",
    "series_inputs",
    "vehicle_series",
]

log = logging.getLogger(__name__)

# The longest reaction delay the models consider (the delay prior's upper bound) sets the history.
HISTORY_SECONDS = 1.5


def history_steps(dt: float) -> int:
    """K: how many past steps the history window holds at sampling interval ``dt``."""
    return math.ceil(HISTORY_SECONDS / dt - 1e-9)


class ExtendedInputs(NamedTuple):
    """One step's inputs for the extensions; the first four fields are the base model's inputs.

    gap, lead_v, has_leader, dt: as in :class:`~bayesdrive.drivers.base.CarFollowingInputs`.
    lead_acc: the leader's acceleration, backward difference of its observed speed (m/s^2).
    gap2: bumper gap to the leader plus the leader's bumper gap to its own leader (m).
    lead2_v: speed of the second vehicle ahead (m/s).
    has_leader2: 1.0 when a second vehicle ahead is known, else 0.0.
    lag_v, lag_gap, lag_lead_v: (K + 1,) ego speed, gap and leader speed k steps ago (k = 0: now).
    prev_dx: the ego's position increment over the previous step (m).
    """

    gap: Array
    lead_v: Array
    has_leader: Array
    dt: Array
    lead_acc: Array
    gap2: Array
    lead2_v: Array
    has_leader2: Array
    lag_v: Array
    lag_gap: Array
    lag_lead_v: Array
    prev_dx: Array

    @property
    def car_following(self) -> CarFollowingInputs:
        """The current-step part, as the base models see it."""
        return CarFollowingInputs(self.gap, self.lead_v, self.has_leader, self.dt)


class ExtendedSeries(NamedTuple):
    """Per-vehicle arrays (vehicle, step), padded; step j goes from sample j to sample j + 1.

    v, next_v, dx, gap, lead_v, has_leader: as in :class:`~bayesdrive.data.views.FollowerArrays`.
    lead_acc, gap2, lead2_v, has_leader2: see :class:`ExtendedInputs` (at sample j).
    usable: the step is a usable car-following step (the ``window="all"`` mask of the views).
    fit, heldout: the steps scored in the fitting / held-out window (usable, with a full history).
    t: time of sample j (s).
    """

    vehicle_ids: tuple[str, ...]
    t: np.ndarray
    v: np.ndarray
    next_v: np.ndarray
    dx: np.ndarray
    gap: np.ndarray
    lead_v: np.ndarray
    has_leader: np.ndarray
    lead_acc: np.ndarray
    gap2: np.ndarray
    lead2_v: np.ndarray
    has_leader2: np.ndarray
    usable: np.ndarray
    fit: np.ndarray
    heldout: np.ndarray
    dt: float

    @property
    def history(self) -> int:
        return history_steps(self.dt)

    def subset(self, rows) -> ExtendedSeries:
        """The same series restricted to some vehicle rows (an index array or slice)."""
        index = np.arange(len(self.vehicle_ids))[rows]
        picked = {
            name: value[index]
            for name, value in self._asdict().items()
            if isinstance(value, np.ndarray)
        }
        return self._replace(vehicle_ids=tuple(self.vehicle_ids[i] for i in index), **picked)


class VehicleSeries(NamedTuple):
    """One vehicle's per-step arrays as JAX arrays (what :func:`inputs_at` reads)."""

    v: Array
    next_v: Array
    dx: Array
    gap: Array
    lead_v: Array
    has_leader: Array
    lead_acc: Array
    gap2: Array
    lead2_v: Array
    has_leader2: Array


def vehicle_series(series: ExtendedSeries, dtype=float) -> VehicleSeries:
    """The (vehicle, step) JAX arrays :func:`inputs_at` and the engines read (default float type)."""
    return VehicleSeries(
        *(jnp.asarray(getattr(series, name), dtype=dtype) for name in VehicleSeries._fields)
    )


def inputs_at(data: VehicleSeries, j: Array, dt: Array, history: int) -> ExtendedInputs:
    """The :class:`ExtendedInputs` of step ``j`` of one vehicle (``data`` fields have shape (S,)).

    Lags reaching before the first sample repeat the first sample; such steps are never scored
    (see the module docstring), so the repetition only keeps the arrays finite.
    """
    lags = jnp.maximum(j - jnp.arange(history + 1), 0)
    return ExtendedInputs(
        gap=data.gap[j],
        lead_v=data.lead_v[j],
        has_leader=data.has_leader[j],
        dt=jnp.asarray(dt, dtype=data.v.dtype),
        lead_acc=data.lead_acc[j],
        gap2=data.gap2[j],
        lead2_v=data.lead2_v[j],
        has_leader2=data.has_leader2[j],
        lag_v=data.v[lags],
        lag_gap=data.gap[lags],
        lag_lead_v=data.lead_v[lags],
        prev_dx=data.dx[jnp.maximum(j - 1, 0)],
    )


def series_inputs(data: VehicleSeries, dt: float, history: int) -> ExtendedInputs:
    """Every step's inputs of one vehicle, stacked along a leading step axis."""
    steps = jnp.arange(data.v.shape[0])
    return jax.vmap(lambda j: inputs_at(data, j, dt, history))(steps)


def _second_vehicle_and_leader_acc(traj: Trajectories) -> pd.DataFrame:
    """Per sample: the second vehicle ahead (gap2, lead2_v) and the leader's acceleration."""
    tracks = traj.tracks
    frame = np.round(tracks["t"].to_numpy() / traj.dt).astype(np.int64)
    own = pd.DataFrame(
        {
            "vehicle_id": tracks["vehicle_id"].to_numpy(),
            "frame": frame,
            "v": tracks["v"].to_numpy(dtype=np.float64),
            "gap": tracks["gap"].to_numpy(dtype=np.float64),
            "leader_id": tracks["leader_id"].to_numpy(),
        }
    )
    previous = own[["vehicle_id", "frame", "v"]].assign(frame=own["frame"] + 1)
    own = own.merge(
        previous.rename(columns={"v": "v_before"}), on=["vehicle_id", "frame"], how="left"
    )
    leader_rows = own.rename(
        columns={
            "vehicle_id": "leader_id",
            "v": "lead_v",
            "gap": "lead_gap",
            "leader_id": "lead2_id",
            "v_before": "lead_v_before",
        }
    )
    joined = own[["vehicle_id", "frame", "gap", "leader_id"]].merge(
        leader_rows, on=["leader_id", "frame"], how="left"
    )
    lead_acc = (joined["lead_v"] - joined["lead_v_before"]) / traj.dt
    second = leader_rows[["leader_id", "frame", "lead_v"]].rename(
        columns={"leader_id": "lead2_id", "lead_v": "lead2_v"}
    )
    joined = joined.merge(second, on=["lead2_id", "frame"], how="left")
    has2 = joined["lead2_v"].notna() & joined["lead_gap"].notna() & joined["gap"].notna()
    return pd.DataFrame(
        {
            "vehicle_id": joined["vehicle_id"],
            "frame": joined["frame"],
            "lead_acc": lead_acc,
            "gap2": np.where(has2, joined["gap"] + joined["lead_gap"], np.nan),
            "lead2_v": np.where(has2, joined["lead2_v"], np.nan),
            "has_leader2": has2.astype(float),
        }
    )


def extended_series(traj: Trajectories, *, vehicle_ids: list[str] | None = None) -> ExtendedSeries:
    """Padded per-step arrays of every follower, with the extras and the fit/held-out masks.

    Built on :func:`~bayesdrive.data.views.follower_arrays` (same steps, same padding, same split
    rule), so the base engines and the criticism agree on every step. Vehicles without a scored
    step in both windows are left out, and the count is logged.
    """
    windows = {
        name: follower_arrays(traj, window=name, vehicle_ids=vehicle_ids)
        for name in ("all", "fit", "heldout")
    }
    every = windows["all"]
    dt = every.dt
    history = history_steps(dt)
    shape = every.mask.shape

    def window_mask(name: str) -> np.ndarray:
        arrays = windows[name]
        out = np.zeros(shape)
        row_of = {vid: i for i, vid in enumerate(arrays.vehicle_ids)}
        for row, vid in enumerate(every.vehicle_ids):
            if vid in row_of:
                width = min(shape[1], arrays.mask.shape[1])
                out[row, :width] = arrays.mask[row_of[vid], :width]
        return out

    usable = every.mask > 0
    full_history = usable.copy()
    for k in range(1, history + 1):
        full_history[:, k:] &= usable[:, :-k]
        full_history[:, :k] = False
    fit = window_mask("fit") * full_history
    heldout = window_mask("heldout") * full_history
    lost = int(usable.sum() - full_history.sum())
    if lost:
        log.info(
            "%d step(s) without a full %.1f s history left out of scoring (all models alike)",
            lost,
            HISTORY_SECONDS,
        )

    extras = _second_vehicle_and_leader_acc(traj).set_index(["vehicle_id", "frame"])
    extra = {name: np.zeros(shape) for name in ("lead_acc", "gap2", "lead2_v", "has_leader2")}
    no_lead_acc = 0
    for row, vid in enumerate(every.vehicle_ids):
        frames = np.round(traj.vehicle(vid)["t"].to_numpy()[:-1] / dt).astype(np.int64)
        rows = extras.loc[[(vid, f) for f in frames]]
        n = len(frames)
        lead_acc = rows["lead_acc"].to_numpy()
        scored = (fit[row, :n] + heldout[row, :n]) > 0
        no_lead_acc += int((~np.isfinite(lead_acc) & scored).sum())
        extra["lead_acc"][row, :n] = np.nan_to_num(lead_acc, nan=0.0)
        extra["gap2"][row, :n] = np.where(rows["has_leader2"] > 0, rows["gap2"], 100.0)
        extra["lead2_v"][row, :n] = np.where(rows["has_leader2"] > 0, rows["lead2_v"], 1.0)
        extra["has_leader2"][row, :n] = rows["has_leader2"].to_numpy()
    if no_lead_acc:
        log.warning(
            "%d scored step(s) have no previous leader sample; their leader acceleration is "
            "taken as 0",
            no_lead_acc,
        )

    keep = (fit.sum(axis=1) > 0) & (heldout.sum(axis=1) > 0)
    if not keep.any():
        raise DataError(
            f"{traj.source}: no vehicle has scored steps in both the fitting and the held-out "
            "window (each needs a leader and a full history)"
        )
    if not keep.all():
        log.warning(
            "%d vehicle(s) without scored steps in both windows left out: %s",
            int((~keep).sum()),
            [vid for vid, k in zip(every.vehicle_ids, keep, strict=True) if not k],
        )
    series = ExtendedSeries(
        vehicle_ids=every.vehicle_ids,
        t=every.t,
        v=every.v,
        next_v=every.next_v,
        dx=every.dx,
        gap=every.gap,
        lead_v=every.lead_v,
        has_leader=every.has_leader,
        lead_acc=extra["lead_acc"],
        gap2=extra["gap2"],
        lead2_v=extra["lead2_v"],
        has_leader2=extra["has_leader2"],
        usable=usable.astype(float),
        fit=fit,
        heldout=heldout,
        dt=dt,
    )
    return series.subset(np.flatnonzero(keep))
