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
from bayesdrive.simulation.follower_rollout import heldout_windows, rollout
from bayesdrive.simulation.posterior import particles_by_vehicle

__all__ = ["LEVELS", "PIT_BINS", "pit_summary", "predictive_calibration"]

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
        out["horizons"][f"{horizon_s:g}"] = pit_summary(pit)
    return out
