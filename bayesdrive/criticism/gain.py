r"""What an extension gains over the base model on held-out data, and whether the gain is real.

**Gain.** For each vehicle, the held-out log predictive density of a model is
:math:`\log p(y_{held} \mid y_{fit})`: the sum of the one-step predictive log densities over the
vehicle's held-out window, each step predicted from everything before it (leave-future-out, not
leave-one-out: the held-out window lies after the fitting window). The tempering sampler gives it
by continuing from the fitting-window posterior (:mod:`bayesdrive.inference.engines.heldout_evidence`). The gain
of an extension is the sum over vehicles of the per-vehicle differences,

.. math::

    G = \sum_n g_n, \qquad g_n = \log p_{ext}(y_{held,n} \mid y_{fit,n})
    - \log p_{base}(y_{held,n} \mid y_{fit,n}),

and its standard error is taken **across vehicles**, :math:`se = \sqrt{N}\, sd(g_n)`: vehicles are
independent, steps within a vehicle are not, so a step-level standard error would be too small
exactly when the model is wrong in an autocorrelated way. The per-vehicle differences include the
sampler's Monte Carlo error, so its noise is counted in the standard error too.

**Significance.** The question is whether drivers' held-out predictions improve, i.e. whether the
per-vehicle gains are shifted above 0. Gains are heavy-tailed across vehicles: a strong effect can
gain 10 000 nats in one vehicle and 200 in the others, and then :math:`G/se` stays near 1 however
many vehicles improve (one outlier sets both the mean and the sd). So the test is a one-sided
t-test, across vehicles with N - 1 degrees of freedom, of the sign-preserving log transform
:math:`h(g) = \mathrm{sign}(g)\log(1 + |g|)` of the gains (odd and increasing, so gains symmetric
about 0 stay so and the null is respected; a nested extension that does not help loses a little
in most vehicles, which makes the test conservative). :math:`G`, :math:`se` and :math:`G/se` are
reported beside it. Trying several extensions is accounted for by Holm's step-down procedure
(Holm 1979) over the **whole family** of causes the criticism knows, whether or not an extension
was fitted: a cause the checks did not point to counts as p = 1, so screening never inflates the
family-wise error rate, which stays below ``alpha`` (0.05) when no extension helps. The verdict is
the significant cause with the largest gain :math:`G`, else "none".

**RMSE change.** The change in root mean square position error of closed-loop rollouts on the
held-out windows (:mod:`bayesdrive.simulation.follower_rollout`), extension minus base, averaged over vehicles
with its standard error across vehicles (negative: the extension simulates closer to the data).

**Forecast gain** (what decides adoption, :func:`forecast_gain`). Per held-out window, the energy
score of the rollouts' joint (gap, speed) path over the whole window (rollouts from the
``filtered`` start, or ``stationary`` where the simulator cannot filter the model's hidden state,
as recorded; :func:`~bayesdrive.simulation.calibration.energy_score`, units 1 m and 1 m/s), averaged
over each vehicle's windows; the gain of vehicle n is the current model's score minus the
extension's (positive: the extension forecasts better), tested by a one-sided paired t-test across
vehicles (N - 1 df; vehicles independent, a vehicle's windows not). Beside it: the change of the
predictive mean's position RMSE at the window's end (extension minus current, per vehicle, averaged
over vehicles) and each model's collisions (rollouts whose simulated gap reached 0).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np
from scipy import stats

from bayesdrive.inference.engines.heldout_evidence import FitResult
from bayesdrive.simulation.calibration import energy_score
from bayesdrive.simulation.follower_rollout import Rollouts

__all__ = [
    "ALPHA",
    "ForecastGain",
    "Gain",
    "elpd_gain",
    "forecast_gain",
    "forecast_gain_from_scores",
    "holm",
    "one_sided_t_test",
    "rmse_change",
    "transformed_t_test",
    "vehicle_energy_scores",
    "vehicle_mean_rmse",
]

log = logging.getLogger(__name__)

ALPHA = 0.05


class Gain(NamedTuple):
    """Held-out predictive gain of one extension over the base model (module docstring).

    elpd, se, t: the summed gain, its se across vehicles and their ratio (reported);
    t_transformed, p_value: the test on the log-transformed per-vehicle gains (decides).
    """

    per_vehicle: np.ndarray
    elpd: float
    se: float
    t: float
    t_transformed: float
    p_value: float


def elpd_gain(base: FitResult, extension: FitResult) -> Gain:
    """Sum over vehicles of the held-out log predictive density gain, its se across vehicles."""
    base_held = np.asarray(base.log_z_held, np.float64)
    if not np.all(np.isfinite(base_held)):
        bad = np.flatnonzero(~np.isfinite(base_held)).tolist()
        raise FloatingPointError(
            f"{base.model.name}: held-out log predictive density not finite for vehicle rows {bad}"
        )
    per_vehicle = np.asarray(extension.log_z_held, np.float64) - base_held
    if not np.all(np.isfinite(per_vehicle)):
        # The extension calls some held-out data impossible (or its sampler broke down there):
        # it cannot be the cause. Reported, never significant.
        bad = np.flatnonzero(~np.isfinite(per_vehicle)).tolist()
        log.warning(
            "%s: held-out log predictive density not finite for vehicle rows %s; the extension "
            "is not significant",
            extension.model.name,
            bad,
        )
        nan = float("nan")
        return Gain(per_vehicle, nan, nan, nan, nan, 1.0)
    n = per_vehicle.size
    total = float(per_vehicle.sum())
    if n < 2:
        return Gain(per_vehicle, total, float("nan"), float("nan"), float("nan"), 1.0)
    se = float(np.sqrt(n) * per_vehicle.std(ddof=1))
    # Identical gains in every vehicle (e.g. the same model twice) carry no evidence either way.
    t = total / se if se > 0 else 0.0
    return Gain(per_vehicle, total, se, t, *transformed_t_test(per_vehicle))


def one_sided_t_test(values: np.ndarray) -> tuple[float, float]:
    """One-sample t-test across vehicles (N - 1 df) that the mean of ``values`` is above 0: (t, p).
    Fewer than two values, or the same value in every vehicle (e.g. the same model twice), carry
    no evidence either way: (0, 1)."""
    values = np.asarray(values, np.float64)
    sd = values.std(ddof=1) if values.size > 1 else 0.0
    if sd == 0:
        return 0.0, 1.0
    t = float(values.mean() / (sd / np.sqrt(values.size)))
    return t, float(stats.t.sf(t, df=values.size - 1))


def transformed_t_test(gains: np.ndarray) -> tuple[float, float]:
    """One-sided t-test across vehicles of sign(g) log(1 + |g|) > 0: (t, p) (module docstring)."""
    return one_sided_t_test(np.sign(gains) * np.log1p(np.abs(gains)))


def holm(p_values: Mapping[str, float], family: Sequence[str], alpha: float = ALPHA) -> set[str]:
    """Holm's step-down rejections over ``family``; members without a p-value count as p = 1."""
    ordered = sorted(family, key=lambda name: p_values.get(name, 1.0))
    rejected: set[str] = set()
    m = len(ordered)
    for rank, name in enumerate(ordered):
        if p_values.get(name, 1.0) > alpha / (m - rank):
            break
        rejected.add(name)
    return rejected


def rmse_change(base_rmse: np.ndarray, extension_rmse: np.ndarray) -> tuple[float, float]:
    """Mean over vehicles of (extension - base) rollout RMSE and its se across vehicles (m)."""
    both = np.isfinite(base_rmse) & np.isfinite(extension_rmse)
    diff = extension_rmse[both] - base_rmse[both]
    if diff.size == 0:
        return float("nan"), float("nan")
    se = float(diff.std(ddof=1) / np.sqrt(diff.size)) if diff.size > 1 else float("nan")
    return float(diff.mean()), se


class ForecastGain(NamedTuple):
    """Held-out forecast gain of an extension over the current model (module docstring).

    per_vehicle: the current model's energy score minus the extension's, per vehicle (NaN: no
    window); mean, se, p_value: their mean over vehicles, its se and the one-sided paired test;
    rmse_mean_change, rmse_mean_change_se: the predictive-mean position RMSE change (m);
    collisions_current, collisions_extension: rollouts whose simulated gap reached 0;
    start: the extension's rollouts' start (``stationary`` where the simulator cannot filter its
    hidden state).
    """

    per_vehicle: np.ndarray
    mean: float
    se: float
    p_value: float
    rmse_mean_change: float
    rmse_mean_change_se: float
    collisions_current: int
    collisions_extension: int
    start: str


def vehicle_energy_scores(rolled: Rollouts, num_vehicles: int) -> np.ndarray:
    """(vehicle,) mean over the vehicle's windows of the energy score of the joint (gap, speed)
    path over the whole window (the gap's error is the position's negated: leader replayed)."""
    if rolled.offset.shape[0] == 0:
        return np.full(num_vehicles, np.nan)
    scores = energy_score(-rolled.offset, rolled.speed_offset)
    return rolled.per_vehicle(scores, num_vehicles)


def vehicle_mean_rmse(rolled: Rollouts, num_vehicles: int) -> np.ndarray:
    """(vehicle,) RMSE over the vehicle's windows of the predictive mean's position at the window's
    end (the mean over rollouts as a point forecast)."""
    if rolled.offset.shape[0] == 0:
        return np.full(num_vehicles, np.nan)
    squared = rolled.offset[:, :, -1].mean(axis=1) ** 2
    return np.sqrt(rolled.per_vehicle(squared, num_vehicles))


def forecast_gain_from_scores(
    current_energy: np.ndarray,
    extension_energy: np.ndarray,
    current_rmse: np.ndarray,
    extension_rmse: np.ndarray,
    collisions_current: int,
    collisions_extension: int,
    start: str,
) -> ForecastGain:
    """The forecast gain from per-vehicle energy scores and predictive-mean RMSEs (module
    docstring); vehicles where either model has no score are left out of the test."""
    per_vehicle = np.asarray(current_energy, np.float64) - np.asarray(extension_energy, np.float64)
    paired = per_vehicle[np.isfinite(per_vehicle)]
    nan = float("nan")
    mean = float(paired.mean()) if paired.size else nan
    se = float(paired.std(ddof=1) / np.sqrt(paired.size)) if paired.size > 1 else nan
    _, p = one_sided_t_test(paired)
    change, change_se = rmse_change(
        np.asarray(current_rmse, np.float64), np.asarray(extension_rmse, np.float64)
    )
    return ForecastGain(
        per_vehicle,
        mean,
        se,
        p,
        change,
        change_se,
        collisions_current,
        collisions_extension,
        start,
    )


def forecast_gain(current: Rollouts, extension: Rollouts, num_vehicles: int) -> ForecastGain:
    """The forecast gain of ``extension``'s rollouts over ``current``'s on the same windows."""
    return forecast_gain_from_scores(
        vehicle_energy_scores(current, num_vehicles),
        vehicle_energy_scores(extension, num_vehicles),
        vehicle_mean_rmse(current, num_vehicles),
        vehicle_mean_rmse(extension, num_vehicles),
        int(current.collisions.sum()),
        int(extension.collisions.sum()),
        extension.start,
    )
