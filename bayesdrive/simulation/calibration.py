"""Forecast scores of a fitted model's predictive on held-out windows: proper scores, calibration.

Every held-out window of the longest lead time (:data:`LEAD_TIMES_S`;
:func:`~bayesdrive.simulation.follower_rollout.heldout_windows`: consecutive, non-overlapping,
every step scored) is forecast by rolling the follower out behind its replayed leader
(:func:`~bayesdrive.simulation.follower_rollout.rollout`, any driver model, each rollout with a
fresh posterior draw of that vehicle), once from each start of :data:`STARTS_SHOWN`: ``filtered``
(the forecast: the model's state filtered from the window's observed history) and ``stationary``
beside it (the same rollouts without that history). A model whose hidden state the simulator
cannot filter gets the start's refusal in place of its scores.

At each lead time the rollouts are scored against the observation by proper scores from
``scoringrules`` (Zamo & Naveau's ensemble estimators): the CRPS of the gap, the position and the
speed (with the leader replayed, the gap's error is the position's negated, so their CRPS agree),
and the energy score of the joint (gap, speed) path from the first step to the lead time, each
variable divided by its unit, :data:`ENERGY_UNITS` (1 m and 1 m/s, fixed beforehand and
independent of the data), so the score is in those units. Beside them, not deciding anything:
the RMSE of the predictive mean, the RMSE over rollouts (what the closed-loop tables report; it
splits exactly into the mean's error and the rollouts' spread,
``rmse_rollouts**2 = rmse_mean**2 + spread**2``, so it penalises a calibrated spread), and the
probability integral transform of the observed position (its rank among the rollouts' end
positions, ties, e.g. two stopped cars, split at random: :func:`pit_of_observation`), whose
central 50% and 90% intervals cover the observation at those rates for a calibrated predictive.
Constant velocity from each window's observed first speed (:func:`constant_velocity_offsets`) is
scored on the same windows: for a point forecast the CRPS is the absolute error.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import numpy as np
import scoringrules
import xarray as xr
from jax import Array
from scipy import stats

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import DriverModel
from bayesdrive.drivers.closed_loop import FILTERED, STATIONARY, check_start
from bayesdrive.drivers.extensions import as_extended
from bayesdrive.simulation.follower_rollout import (
    Rollouts,
    RolloutWindows,
    heldout_windows,
    rollout,
)
from bayesdrive.simulation.posterior import particles_by_vehicle

__all__ = [
    "ENERGY_UNITS",
    "LEAD_TIMES_S",
    "LEVELS",
    "PIT_BINS",
    "STARTS_SHOWN",
    "by_vehicle_difference",
    "constant_velocity_offsets",
    "crps",
    "energy_score",
    "forecast_scores",
    "pit_of_observation",
    "pit_summary",
    "point_scores",
    "predictive_calibration",
]

LEVELS = (0.5, 0.9)
PIT_BINS = 10
LEAD_TIMES_S = (1.0, 2.0, 3.0, 5.0)
# The energy score's units of the gap (m) and the speed (m/s): stated, not estimated from data.
ENERGY_UNITS = {"gap_m": 1.0, "speed_mps": 1.0}
STARTS_SHOWN = (FILTERED, STATIONARY)


def pit_summary(pit: np.ndarray) -> dict[str, Any]:
    """Coverage of the central intervals of :data:`LEVELS`, the :data:`PIT_BINS`-bin histogram
    and its chi-square test against uniform (descriptive: windows of one vehicle are dependent)."""
    counts, _ = np.histogram(pit, bins=PIT_BINS, range=(0.0, 1.0))
    summary: dict[str, Any] = {"windows": int(pit.size), "pit_counts": counts.tolist()}
    for level in LEVELS:
        summary[f"coverage_{round(level * 100)}"] = (
            float(np.mean(np.abs(pit - 0.5) < level / 2)) if pit.size else None
        )
    summary["pit_chi2_p"] = float(stats.chisquare(counts).pvalue) if pit.size else None
    return summary


def pit_of_observation(errors: np.ndarray, ties: np.ndarray | float) -> np.ndarray:
    """(row,) rank PIT of the observation among each row's ensemble of forecast errors (row,
    member; simulated minus observed): with ``b`` of the ``m`` members below it and ``q`` equal to
    it, (b + w (q + 1)) / (m + 1), ``w`` = ``ties`` (a uniform draw per row, or 0.5 for the
    mid-rank).

    An observation exchangeable with the members has a rank uniform on 0..m (ties broken at
    random), so with a uniform ``w`` the PIT is exactly uniform on (0, 1) (the randomised PIT of
    an ensemble; Gneiting, Balabdaoui & Raftery 2007). The share of members below it, b / m, is
    not: it puts 1 / (m + 1) on each of 0 and 1, and the central 90% interval of a calibrated
    ensemble of 100 held 90 of its 101 values (0.89; 0.95 fell inside in floating point, 0.05
    did not)."""
    members = errors.shape[1]
    below = (errors < 0.0).sum(axis=1)
    equal = (errors == 0.0).sum(axis=1)
    return (below + ties * (equal + 1)) / (members + 1)


def crps(errors: np.ndarray) -> np.ndarray:
    """(row,) CRPS of each row's ensemble of forecast errors (simulated minus observed) at 0."""
    return np.asarray(scoringrules.crps_ensemble(np.zeros(errors.shape[0]), errors, m_axis=1))


def energy_score(gap_errors: np.ndarray, speed_errors: np.ndarray) -> np.ndarray:
    """(row,) energy score of each row's ensemble of joint (gap, speed) path errors, each
    (row, member, step), every variable divided by its unit in :data:`ENERGY_UNITS`."""
    path = np.concatenate(
        [gap_errors / ENERGY_UNITS["gap_m"], speed_errors / ENERGY_UNITS["speed_mps"]], axis=2
    )
    return np.asarray(scoringrules.es_ensemble(np.zeros(path[:, 0].shape), path))


def by_vehicle_difference(difference: np.ndarray, row: np.ndarray) -> dict[str, float | int | None]:
    """Mean over vehicles of each vehicle's mean of ``difference`` over its windows (``row``:
    each window's vehicle), with a 95% t interval across vehicles: a driver's windows are
    dependent, drivers are the independent units."""
    vehicles = np.unique(row)
    means = np.array([difference[row == v].mean() for v in vehicles])
    out: dict[str, float | int | None] = {"vehicles": len(means), "mean": None}
    out.update(low=None, high=None)
    if len(means) == 0:
        return out
    out["mean"] = float(means.mean())
    if len(means) > 1:
        half = stats.t.ppf(0.975, len(means) - 1) * means.std(ddof=1) / np.sqrt(len(means))
        out.update(low=out["mean"] - half, high=out["mean"] + half)
    return out


def point_scores(end_offsets: np.ndarray) -> dict[str, float | None]:
    """Point scores of ``end_offsets`` (window, rollout): simulated minus observed position at
    the window's end (m). ``rmse_rollouts_m`` over windows and rollouts, ``rmse_mean_m`` of the
    mean over rollouts (the predictive mean as a point forecast), ``spread_m`` the root mean
    within-window variance, ``crps_m`` the mean CRPS of the rollouts' empirical distribution
    (``E|X - y| - E|X - X'| / 2``, the latter from the sorted sample), ``mae_median_m`` the
    absolute error of the predictive median."""
    offsets = np.asarray(end_offsets, np.float64)
    if offsets.shape[0] == 0:
        keys = ("rmse_rollouts_m", "rmse_mean_m", "spread_m", "crps_m", "mae_median_m")
        return dict.fromkeys(keys)
    return {
        "rmse_rollouts_m": float(np.sqrt(np.mean(offsets**2))),
        "rmse_mean_m": float(np.sqrt(np.mean(offsets.mean(axis=1) ** 2))),
        "spread_m": float(np.sqrt(np.mean(offsets.var(axis=1)))),
        "crps_m": float(crps(offsets).mean()),
        "mae_median_m": float(np.mean(np.abs(np.median(offsets, axis=1)))),
    }


def constant_velocity_offsets(
    series: FollowerArrays, windows: RolloutWindows, lead_time_s: float | None = None
) -> np.ndarray:
    """(window,) position ``lead_time_s`` after each window's start (default: at its end) of
    constant velocity from the window's first observed speed, minus the observed position (m)."""
    horizon = windows.horizon if lead_time_s is None else round(lead_time_s / series.dt)
    steps = windows.start[:, None] + np.arange(horizon)[None, :]
    travelled = series.dx[windows.row[:, None], steps].sum(axis=1)
    return horizon * series.dt * series.v[windows.row, windows.start] - travelled


def forecast_scores(key: Array, rolled: Rollouts, dt: float, lead_time_s: float) -> dict[str, Any]:
    """The scores of ``rolled`` at ``lead_time_s`` (module docstring); ``key`` breaks PIT ties."""
    steps = round(lead_time_s / dt)
    position = rolled.offset[:, :, steps - 1]
    speed = rolled.speed_offset[:, :, steps - 1]
    # The joint path of steps 1..lead time.
    energy = energy_score(-rolled.offset[:, :, :steps], rolled.speed_offset[:, :, :steps])
    pit = pit_of_observation(position, np.asarray(jax.random.uniform(key, position.shape[:1])))
    windows = position.shape[0]
    return {
        **pit_summary(pit),
        **point_scores(position),
        "crps_gap_m": float(crps(-position).mean()) if windows else None,
        "crps_speed_mps": float(crps(speed).mean()) if windows else None,
        "energy_score": float(energy.mean()) if windows else None,
        "collisions": int(rolled.collisions.sum()),
    }


def predictive_calibration(
    key: Array,
    model: DriverModel,
    tree: xr.DataTree,
    series: FollowerArrays,
    *,
    lead_times_s: Sequence[float] = LEAD_TIMES_S,
    num_rollouts: int = 100,
) -> dict[str, Any]:
    """Forecast scores of ``model``'s predictive (fitted as ``tree``, every parameter of ``model``
    inferred) on the held-out windows of ``series`` (a ``scored_series``) at each lead time, per
    start of :data:`STARTS_SHOWN`; vehicles of ``series`` without a posterior in ``tree`` are left
    out and counted."""
    draws = particles_by_vehicle(tree, model.param_names)
    rows = [i for i, v in enumerate(series.vehicle_ids) if v in draws]
    kept = series.subset(rows)
    theta = np.stack([draws[v] for v in kept.vehicle_ids])
    windows = heldout_windows(kept, max(lead_times_s))
    out: dict[str, Any] = {
        "vehicles": len(rows),
        "vehicles_without_fit": len(series.vehicle_ids) - len(rows),
        "rollouts": num_rollouts,
        "windows": len(windows.row),
        "window_s": max(lead_times_s),
        "energy_units": ENERGY_UNITS,
        "starts": {},
    }
    # Every start rolls out with the same key: common random numbers sharpen their difference.
    key_rollout, key_ties = jax.random.split(key)
    for start in STARTS_SHOWN:
        try:
            check_start(model, start, has_past=True, whole_history=True)
        except ValueError as refused:
            out["starts"][start] = {"error": str(refused)}
            continue
        rolled = rollout(
            key_rollout,
            as_extended(model),
            theta,
            kept,
            windows,
            num_rollouts=num_rollouts,
            start=start,
        )
        horizons = {}
        for lead_time_s, key_lead in zip(
            lead_times_s, jax.random.split(key_ties, len(lead_times_s)), strict=True
        ):
            scores = forecast_scores(key_lead, rolled, kept.dt, lead_time_s)
            end = rolled.offset[:, :, round(lead_time_s / kept.dt) - 1]
            cv_at = constant_velocity_offsets(kept, windows, lead_time_s)
            horizons[f"{lead_time_s:g}"] = {
                **scores,
                "constant_velocity_rmse_m": float(np.sqrt(np.mean(cv_at**2)))
                if cv_at.size
                else None,
                "constant_velocity_mae_m": float(np.mean(np.abs(cv_at))) if cv_at.size else None,
                "minus_constant_velocity": {
                    "crps_minus_abs_error_m": by_vehicle_difference(
                        crps(end) - np.abs(cv_at), windows.row
                    ),
                    "squared_error_of_mean_minus_squared_error_m2": by_vehicle_difference(
                        end.mean(axis=1) ** 2 - cv_at**2, windows.row
                    ),
                },
            }
        out["starts"][start] = {"horizons": horizons}
    return out
