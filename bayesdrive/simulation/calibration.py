"""Calibration of a fitted model's predictive on held-out windows: interval coverage and PIT.

For every held-out window of ``horizon_s`` seconds (:func:`~bayesdrive.simulation.follower_rollout.heldout_windows`:
consecutive, non-overlapping, every step scored; a one-step horizon makes every scored held-out
step a window) the follower is rolled out from the observed state behind its replayed leader
(:func:`~bayesdrive.simulation.follower_rollout.rollout`, any driver model, each rollout with a
fresh posterior draw of that vehicle). The probability integral transform of the observed
position at the end of the window is the share of rollouts that end behind it (ties, e.g. two
stopped cars, split at random), so a calibrated predictive gives uniform PITs, and its central
50% and 90% intervals cover the observation at those rates: coverage is the share of windows
whose PIT lies within (0.25, 0.75) and (0.05, 0.95).

Beside calibration, the same rollouts give point scores of the position at the window's end
(:func:`point_scores`): the RMSE over rollouts (what the closed-loop tables report for a
stochastic model) splits exactly into the error of the predictive mean and the rollouts' spread,
``rmse_rollouts**2 = rmse_mean**2 + spread**2``; the CRPS is a proper score of the whole
predictive, and for a point forecast it is the absolute error. Constant velocity from each
window's observed first speed (:func:`constant_velocity_offsets`) is scored on the same windows,
so a stochastic model and a point forecast can be compared fairly.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import numpy as np
import xarray as xr
from jax import Array
from scipy import stats

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import DriverModel
from bayesdrive.drivers.extensions import as_extended
from bayesdrive.simulation.follower_rollout import RolloutWindows, heldout_windows, rollout
from bayesdrive.simulation.posterior import particles_by_vehicle

__all__ = [
    "LEVELS",
    "PIT_BINS",
    "by_vehicle_difference",
    "constant_velocity_offsets",
    "pit_summary",
    "point_scores",
    "predictive_calibration",
]

LEVELS = (0.5, 0.9)
PIT_BINS = 10


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


def _crps(offsets: np.ndarray) -> np.ndarray:
    """(window,) CRPS of each row's empirical distribution at 0: ``E|X| - E|X - X'| / 2``, the
    mean pair distance from the sorted sample, ``2 sum_i (2i - R - 1) x_(i) / R**2``."""
    num_rollouts = offsets.shape[1]
    weights = 2.0 * np.arange(1, num_rollouts + 1) - num_rollouts - 1
    mean_pair_distance = 2.0 * (np.sort(offsets, axis=1) @ weights) / num_rollouts**2
    return np.abs(offsets).mean(axis=1) - 0.5 * mean_pair_distance


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
        "crps_m": float(_crps(offsets).mean()),
        "mae_median_m": float(np.mean(np.abs(np.median(offsets, axis=1)))),
    }


def constant_velocity_offsets(series: FollowerArrays, windows: RolloutWindows) -> np.ndarray:
    """(window,) position at each window's end of constant velocity from the window's first
    observed speed, minus the observed position there (m)."""
    steps = windows.start[:, None] + np.arange(windows.horizon)[None, :]
    travelled = series.dx[windows.row[:, None], steps].sum(axis=1)
    return windows.horizon * series.dt * series.v[windows.row, windows.start] - travelled


def predictive_calibration(
    key: Array,
    model: DriverModel,
    tree: xr.DataTree,
    series: FollowerArrays,
    *,
    horizons_s: Sequence[float],
    num_rollouts: int = 100,
) -> dict[str, Any]:
    """PIT and interval coverage of ``model``'s predictive (fitted as ``tree``, every parameter of
    ``model`` inferred) on the held-out windows of ``series`` (a ``scored_series``), for each
    horizon; vehicles of ``series`` without a posterior in ``tree`` are left out and counted."""
    draws = particles_by_vehicle(tree, model.param_names)
    rows = [i for i, v in enumerate(series.vehicle_ids) if v in draws]
    kept = series.subset(rows)
    theta = np.stack([draws[v] for v in kept.vehicle_ids])
    out: dict[str, Any] = {
        "vehicles": len(rows),
        "vehicles_without_fit": len(series.vehicle_ids) - len(rows),
        "rollouts": num_rollouts,
        "horizons": {},
    }
    for horizon_s in horizons_s:
        key, key_rollout, key_ties = jax.random.split(key, 3)
        windows = heldout_windows(kept, horizon_s)
        rolled = rollout(
            key_rollout, as_extended(model), theta, kept, windows, num_rollouts=num_rollouts
        )
        end = rolled.offset[:, :, -1]
        behind, level = (end < 0.0).mean(axis=1), (end == 0.0).mean(axis=1)
        pit = behind + level * np.asarray(jax.random.uniform(key_ties, behind.shape))
        cv = constant_velocity_offsets(kept, windows)
        out["horizons"][f"{horizon_s:g}"] = {
            **pit_summary(pit),
            **point_scores(end),
            "constant_velocity_rmse_m": float(np.sqrt(np.mean(cv**2))) if cv.size else None,
            "constant_velocity_mae_m": float(np.mean(np.abs(cv))) if cv.size else None,
            "minus_constant_velocity": {
                "crps_minus_abs_error_m": by_vehicle_difference(
                    _crps(end) - np.abs(cv), windows.row
                ),
                "squared_error_of_mean_minus_squared_error_m2": by_vehicle_difference(
                    end.mean(axis=1) ** 2 - cv**2, windows.row
                ),
            },
        }
    return out
