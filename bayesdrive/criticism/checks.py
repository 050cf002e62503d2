r"""Checks that show where a fitted base model misfits, on held-out windows: a number and a picture each.

Everything starts from the **one-step posterior predictive** of every scored held-out step: for
``num_draws`` draws :math:`\theta_m` of the fitting-window posterior, the base model predicts the
position increment as :math:`N(v\Delta t + a_m\Delta t^2/2,\ (\sigma_m \Delta t^2/2)^2)` (the
Gaussian execution noise of the base models, :mod:`bayesdrive.drivers.idm`). The probability
integral transform (PIT) of the observed increment, averaged over draws, is uniform for a
calibrated model; its normal quantile :math:`z_t = \Phi^{-1}(PIT_t)` (the *quantile residual*,
Dunn & Smyth 1996) is then close to white Gaussian noise. A step that ends in an observed stop
has a censored increment: its PIT is drawn uniformly below the predicted stop probability
(randomised PIT), with a key of its own.

The checks (``Check.name``):

* ``calibration``: PIT histogram (chi-square against uniform) and coverage of the central 50% and
  90% one-step predictive intervals.
* ``autocorrelation``: autocorrelation of :math:`z` at lags 1..30 within vehicles. Positive lag-1
  correlation points to autocorrelated noise, negative to measurement noise on positions (the
  difference of two noisy readings is an MA(1) with correlation -1/2), a slowly decaying positive
  tail (lags 10-30) to drifting parameters.
* ``leader_cross_correlation``: correlation of :math:`z_t` with the leader's acceleration
  :math:`k` steps earlier (k = 0..K, the history window): a response to the leader's past actions
  points to a reaction delay.
* ``variance_vs_*``: :math:`z_t^2 - 1` against speed, gap, relative speed and time in the window
  (a calibrated model has mean 0 everywhere); a trend in speed points to speed-dependent noise.
  ``mean_vs_*``: :math:`z_t` itself against the same covariates (a biased mean).
* ``change_points``: per vehicle, the CUSUM of :math:`z` scaled by its long-run sd (sup of a
  Brownian bridge under the null, Kolmogorov's distribution); many vehicles with a change point
  point to drifting parameters.
* ``gain_drift``: per vehicle, over its whole record (both windows), the slope of :math:`z` on the
  predicted acceleration in blocks of :data:`GAIN_BLOCK_S`, tested for equality across blocks,
  the vehicles' p-values combined by Stouffer's method: a rule whose strength changes in time (a drifting maximum acceleration scales the whole
  rule) leaves a residual proportional to the predicted acceleration with a slope that moves.
  No extension models it, so it points to no cause; a misfit all the same.
* ``score_<cause>``: the score (Lagrange-multiplier) test of each extension against the base
  model: the slope of the held-out log-likelihood in the extension's (first) parameter at the
  values that switch it off (the base model), at the base posterior draws, with the execution-noise sd
  profiled out: the slope minus its regression on the slope in sigma over the vehicle's held-out
  steps (the efficient score). Without that projection a noise-scale extension's slope is mostly
  a change of the noise level between the fitting and the held-out window: speed-dependent noise
  on a platoon that slows down late gave a slope of the wrong sign (z = -2.5 on generated data
  where the extension gained on every vehicle). Its sum over vehicles divided by the root sum of
  squares of the per-vehicle slopes is approximately N(0, 1) when the base model is right
  (self-normalised across vehicles, so autocorrelation within a vehicle does no harm); one-sided,
  where the extension's "off" value is its parameter's lower bound. An extension whose "off"
  values lie inside their bounds (coefficients of either sign, as the state correction's) is
  tested in all its parameters at once and in both directions: Hotelling's :math:`T^2` of the
  vehicles' vectors of efficient scores (mean 0 when the base model is right; vehicles
  independent, their covariance estimated across them), F-distributed on (k, N - k) degrees of
  freedom for k parameters and N vehicles under Gaussian per-vehicle scores. The self-normalised
  quadratic form of the one-parameter test would be bounded by N (p >= 0.046 for three
  parameters and 8 vehicles however strong the effect), so it is not used there.

* ``lag1_by_vehicle``, ``long_lag_by_vehicle``: the autocorrelations above per vehicle, tested
  across vehicles (negative lag 1: measurement noise; positive long lags: drifting parameters).
* ``noise_vs_speed_by_vehicle``: per vehicle, the rank correlation of |z| with speed, tested
  across vehicles (speed-dependent noise; the score test above misses it, see the check).
* ``multistep`` (with rollouts): closed-loop coverage of the observed position by the rollouts'
  band, and whether observations fall in the rollouts' tails too often, tested across vehicles;
  it points to no cause, but a failure is a misfit all the same.

Pooled correlation p-values use the white-noise standard error :math:`1/\sqrt{n}` (Bartlett); with
several lags the smallest is Bonferroni-corrected over lags. Pooled over thousands of
autocorrelated steps they flag the smallest misfit, so they describe; only the checks whose
p-value is calibrated across vehicles (score tests, per-vehicle autocorrelations; ``screening``)
decide which extensions are fitted. The verdict rests on the held-out predictive gain
(:mod:`bayesdrive.criticism.gain`).
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from scipy import stats

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import EgoState, fill_params
from bayesdrive.drivers.execution_noise import STOP_SPEED, increment_law
from bayesdrive.drivers.extensions import extend
from bayesdrive.drivers.extensions.compose import ExtendedModel
from bayesdrive.inference.core.likelihood import StepInputs, step_inputs, step_logpdfs
from bayesdrive.inference.engines.heldout_evidence import FitResult
from bayesdrive.simulation.follower_rollout import Rollouts

__all__ = [
    "ACF_LAGS",
    "Check",
    "Residuals",
    "autocorrelation_check",
    "calibration_check",
    "change_point_check",
    "covariate_checks",
    "gain_drift_check",
    "leader_cross_correlation_check",
    "multistep_check",
    "noise_speed_by_vehicle_check",
    "predictive_residuals",
    "run_checks",
    "score_check",
    "vehicle_autocorrelation_checks",
]

ACF_LAGS = 30
DRIFT_LAGS = (10, 30)  # the lag band whose mean autocorrelation points to drifting parameters
PIT_BINS = 10
COVARIATE_BINS = 8
MIN_RANK_STEPS = 20  # scored steps a vehicle needs for its rank correlation of |z| with speed
# Shorter than the slowest drift of interest (periods of tens of seconds), long enough that
# the seconds-long swings of a rule that fits on average (its misfit differs between regimes)
# average out within a block instead of passing for a moving gain.
GAIN_BLOCK_S = 10.0


class Check(NamedTuple):
    """One check: a headline number, its p-value, the causes it points to, and plot data.

    statistic: the headline number (its meaning is in ``summary["statistic"]``).
    p_value: how surprising that number is if the base model is right (None: descriptive only).
    points_to: causes a small p-value points to.
    summary: JSON-ready numbers for the report.
    figure: arrays for :mod:`bayesdrive.reports.criticism_plots`.
    screening: the p-value is calibrated across vehicles (vehicles independent, steps within one
        vehicle not), so it can decide which extensions to fit. Pooled step-level checks are
        descriptive: with thousands of autocorrelated steps their p-values are tiny for the
        smallest misfit (posterior uncertainty alone), so they never screen.
    """

    name: str
    title: str
    statistic: float
    p_value: float | None
    points_to: tuple[str, ...]
    summary: dict[str, Any]
    figure: dict[str, Any]
    screening: bool = False


class Residuals(NamedTuple):
    """Posterior-predictive quantities of every step (vehicle, step): ``mask`` marks the held-out
    steps the checks score, ``usable`` every step with a residual (either window), and
    ``acceleration`` is the draw-averaged predicted mean acceleration (m/s^2)."""

    pit: np.ndarray
    z: np.ndarray
    mask: np.ndarray
    usable: np.ndarray
    acceleration: np.ndarray


@functools.partial(jax.jit, static_argnums=(0, 1))
def _pit_parts(extended: ExtendedModel, names: tuple[str, ...], theta: Array, steps: StepInputs):
    """Draw-averaged P(increment <= observed), P(stop) and predicted mean acceleration of every
    step: (vehicle, step) each."""
    model = extended.model

    def per_step(params, inputs, v, dx):
        state = model.lift(params, EgoState(jnp.zeros_like(v), v), inputs)
        acceleration = model.mean_acceleration(params, state, inputs)
        law = increment_law(v, acceleration, model.noise_sd(params, state), inputs.dt)
        below = jax.scipy.stats.norm.cdf(dx, law.mean, law.sd)
        return below, jax.scipy.stats.norm.cdf(law.stop_z), acceleration

    def per_vehicle(theta_v, steps_v):
        def per_draw(th):
            params = fill_params(model, names, th)
            return jax.vmap(lambda i, v, dx: per_step(params, i, v, dx))(
                steps_v.inputs, steps_v.v, steps_v.dx
            )

        return jax.tree.map(lambda part: part.mean(axis=0), jax.vmap(per_draw)(theta_v))

    return jax.vmap(per_vehicle)(theta, steps)


def predictive_residuals(
    key: Array, fit: FitResult, steps: StepInputs, *, num_draws: int = 64
) -> Residuals:
    """PIT and quantile residuals of every held-out step under the fitted model (module docstring).

    The fitted model must be a base model (mean acceleration plus N(0, sigma^2) execution noise).
    """
    extended = fit.model
    if extended.new_params:
        raise ValueError(f"checks describe a base model's misfit; got {extended.name}")
    draws = np.linspace(0, fit.theta.shape[1] - 1, min(num_draws, fit.theta.shape[1])).astype(int)
    theta = jnp.asarray(fit.theta[:, draws], dtype=steps.v.dtype)
    below, stop, acceleration = (
        np.asarray(part, np.float64) for part in _pit_parts(extended, fit.names, theta, steps)
    )
    stopped = np.asarray(steps.next_v) <= STOP_SPEED
    uniform = np.asarray(jax.random.uniform(key, below.shape))
    # A moving step's PIT is the continuous part above the stop mass; a stop's is randomised.
    pit = np.where(stopped, uniform * stop, stop + (1.0 - stop) * below)
    pit = np.clip(pit, 1e-9, 1.0 - 1e-9)
    return Residuals(
        pit=pit,
        z=stats.norm.ppf(pit),
        mask=np.asarray(steps.heldout) > 0,
        usable=(np.asarray(steps.fit) > 0) | (np.asarray(steps.heldout) > 0),
        acceleration=acceleration,
    )


def calibration_check(res: Residuals) -> Check:
    """PIT histogram and central-interval coverage of the one-step predictive."""
    pit = res.pit[res.mask]
    counts, edges = np.histogram(pit, bins=PIT_BINS, range=(0.0, 1.0))
    chi2 = stats.chisquare(counts)
    coverage = {
        f"coverage_{int(level * 100)}": float(np.mean(np.abs(pit - 0.5) <= level / 2))
        for level in (0.5, 0.9)
    }
    return Check(
        name="calibration",
        title="One-step predictive calibration (PIT)",
        statistic=float(chi2.statistic),
        p_value=float(chi2.pvalue),
        points_to=("speed_dependent_noise", "measurement_noise"),
        summary={
            "statistic": f"chi-square of the {PIT_BINS}-bin PIT histogram against uniform",
            "steps": int(pit.size),
            **coverage,
        },
        figure={"counts": counts, "edges": edges, **coverage},
    )


def _pooled_correlation(a: np.ndarray, b: np.ndarray, mask_a, mask_b, lag: int):
    """Correlation of a[t] with b[t - lag] over pairs where both are used; returns (r, pairs)."""
    if lag > 0:
        a, mask_a = a[:, lag:], mask_a[:, lag:]
        b, mask_b = b[:, :-lag], mask_b[:, :-lag]
    both = mask_a & mask_b
    x, y = a[both], b[both]
    if x.size < 3 or x.std() == 0 or y.std() == 0:
        return 0.0, int(x.size)
    return float(np.corrcoef(x, y)[0, 1]), int(x.size)


def autocorrelation_check(res: Residuals) -> Check:
    """Autocorrelation of the quantile residuals within vehicles at lags 1..ACF_LAGS."""
    acf, pairs = zip(
        *(
            _pooled_correlation(res.z, res.z, res.mask, res.mask, lag)
            for lag in range(1, ACF_LAGS + 1)
        ),
        strict=True,
    )
    acf, pairs = np.asarray(acf), np.asarray(pairs)
    z1 = acf[0] * np.sqrt(pairs[0])
    band = slice(DRIFT_LAGS[0] - 1, DRIFT_LAGS[1])
    # Under white noise the band's lags are nearly independent, each with sd 1/sqrt(pairs).
    drift_z = float(acf[band].sum() / np.sqrt(np.sum(1.0 / pairs[band])))
    p_two_sided = float(2 * stats.norm.sf(abs(z1)))
    return Check(
        name="autocorrelation",
        title="Autocorrelation of quantile residuals",
        statistic=float(acf[0]),
        p_value=p_two_sided,
        # Directional p-values in the summary say which: + lag 1, - lag 1, long-lag tail.
        points_to=("autocorrelated_noise", "measurement_noise", "drifting_parameters"),
        summary={
            "statistic": "lag-1 autocorrelation of z",
            "lag1": float(acf[0]),
            "lag1_z": float(z1),
            "p_positive": float(stats.norm.sf(z1)),
            "p_negative": float(stats.norm.cdf(z1)),
            "long_lag_mean": float(acf[band].mean()),
            "long_lag_z": drift_z,
            "p_long_lag": float(stats.norm.sf(drift_z)),
        },
        figure={"lags": np.arange(1, ACF_LAGS + 1), "acf": acf, "band": 1.96 / np.sqrt(pairs)},
    )


def _t_across_vehicles(values: np.ndarray) -> tuple[float, float, float]:
    """One-sample t statistic of per-vehicle values against 0 (N - 1 df) and its one-sided
    p-values (positive, negative); 0 when there are fewer than 2 values or no spread."""
    if values.size < 2 or values.std(ddof=1) == 0:
        t = 0.0
    else:
        t = float(values.mean() / (values.std(ddof=1) / np.sqrt(values.size)))
    df = max(values.size - 1, 1)
    return t, float(stats.t.sf(t, df=df)), float(stats.t.cdf(t, df=df))


def _vehicle_values_check(
    name: str,
    title: str,
    values: np.ndarray,
    points_to: tuple[str, ...],
    meaning: str,
    p_value: float,
    t: float,
    **tails: float,
) -> Check:
    """A screening check of one value per vehicle: the headline is their mean (0 for none),
    ``meaning`` says what it is, ``t`` and ``p_value`` come from its test across vehicles
    (:func:`_t_across_vehicles`) and ``tails`` are that test's one-sided p-values to report."""
    return Check(
        name=name,
        title=title,
        statistic=float(values.mean()) if values.size else 0.0,
        p_value=p_value,
        points_to=points_to,
        summary={"statistic": meaning, "t": t, "vehicles": int(values.size), **tails},
        figure={"values": values},
        screening=True,
    )


def vehicle_autocorrelation_checks(res: Residuals) -> list[Check]:
    """Per-vehicle autocorrelation of z, tested across vehicles (screening checks).

    For each vehicle: the lag-1 autocorrelation and the mean autocorrelation over lags 10-30.
    One-sample t-tests across vehicles (N - 1 df): a negative mean lag-1 correlation points to
    measurement noise on positions, a positive long-lag mean to drifting parameters.
    """
    lag1, long_lag = [], []
    for z, used in zip(res.z, res.mask, strict=True):
        if used.sum() <= DRIFT_LAGS[1] + 10:
            continue
        row, ok = z[None, :], used[None, :]
        lag1.append(_pooled_correlation(row, row, ok, ok, 1)[0])
        band = range(DRIFT_LAGS[0], DRIFT_LAGS[1] + 1)
        long_lag.append(np.mean([_pooled_correlation(row, row, ok, ok, k)[0] for k in band]))
    checks = []
    for name, values, causes, title in (
        ("lag1_by_vehicle", lag1, ("measurement_noise", "drifting_parameters"), "lag-1"),
        ("long_lag_by_vehicle", long_lag, ("drifting_parameters",), "lags 10-30"),
    ):
        values = np.asarray(values)
        t, p_positive, p_negative = _t_across_vehicles(values)
        # Negative lag 1: measurement noise; positive: drift (or AR noise, which has its own
        # score test); positive long lags: drift.
        checks.append(
            _vehicle_values_check(
                name,
                f"Per-vehicle {title} autocorrelation of z, across vehicles",
                values,
                causes,
                f"mean over vehicles of the per-vehicle {title} autocorrelation",
                min(p_positive, p_negative) if name == "lag1_by_vehicle" else p_positive,
                t,
                p_positive=p_positive,
                p_negative=p_negative,
            )
        )
    return checks


def noise_speed_by_vehicle_check(res: Residuals, series: FollowerArrays) -> Check:
    """Does the residual spread grow with speed within a vehicle? (screening check)

    For each vehicle with at least :data:`MIN_RANK_STEPS` scored steps at more than one speed:
    Spearman's rank correlation of |z| with the speed over its held-out steps; a one-sided
    t-test across vehicles (N - 1 df). Ranks keep a few large residuals from deciding; within a
    vehicle, so that vehicles driving at different speeds with different noise levels (which the
    pooled ``variance_vs_speed`` mixes) do not; the noise level cancels (a level shift between
    the fitting and the held-out window changes no rank). The score test of speed-dependent noise
    projects out the execution-noise sd with the steps' own squared scores, which weighs the
    fast, noisy steps most exactly where the noise grows with speed, and loses the effect.
    """
    values = []
    for z, used, v in zip(res.z, res.mask, np.asarray(series.v), strict=True):
        speeds = v[used]
        if used.sum() < MIN_RANK_STEPS or np.ptp(speeds) == 0:
            continue
        values.append(stats.spearmanr(speeds, np.abs(z[used])).statistic)
    values = np.asarray(values, np.float64)
    values = values[np.isfinite(values)]  # |z| of one value throughout has no rank correlation
    t, p_positive, _ = _t_across_vehicles(values)
    return _vehicle_values_check(
        "noise_vs_speed_by_vehicle",
        "Per-vehicle rank correlation of |z| with speed, across vehicles",
        values,
        ("speed_dependent_noise",),
        "mean over vehicles of Spearman's correlation of |z| with speed",
        p_positive,
        t,
    )


def leader_cross_correlation_check(res: Residuals, series: FollowerArrays) -> tuple[Check, Check]:
    """Correlation of z[t] with the leader's acceleration at t - k, k = 0..history: per vehicle
    (a portmanteau tested across vehicles, for screening) and pooled (the picture)."""
    lead_acc = series.ahead.lead_acc
    usable = series.mask > 0
    lags = np.arange(series.history + 1)
    ccf, pairs = zip(
        *(_pooled_correlation(res.z, lead_acc, res.mask, usable, int(k)) for k in lags),
        strict=True,
    )
    ccf, pairs = np.asarray(ccf), np.asarray(pairs)
    zs = ccf * np.sqrt(pairs)
    worst = int(np.argmax(np.abs(zs)))
    p = float(min(1.0, len(lags) * 2 * stats.norm.sf(abs(zs[worst]))))
    # Per vehicle, a portmanteau of the same cross-correlations: Q = n * sum_k r_k^2 is about
    # chi-square with K + 1 df for white residuals; its excess is tested across vehicles.
    excess = []
    for row in range(res.z.shape[0]):
        per_lag = [
            _pooled_correlation(
                res.z[row : row + 1],
                lead_acc[row : row + 1],
                res.mask[row : row + 1],
                usable[row : row + 1],
                int(k),
            )
            for k in lags
        ]
        if per_lag[0][1] > 3 * len(lags):
            excess.append(sum(n * r**2 for r, n in per_lag) - len(lags))
    excess = np.asarray(excess, np.float64)
    t_excess, p_excess, _ = _t_across_vehicles(excess)
    by_vehicle = _vehicle_values_check(
        "leader_response_by_vehicle",
        "Per-vehicle response to the leader's past accelerations, across vehicles",
        excess,
        ("reaction_delay",),
        "mean over vehicles of n * sum over lags of squared cross-correlations, minus its "
        "white-noise expectation (the number of lags)",
        p_excess,
        t_excess,
    )
    return by_vehicle, Check(
        name="leader_cross_correlation",
        title="Residuals against the leader's past accelerations",
        statistic=float(ccf[worst]),
        p_value=p,
        points_to=("reaction_delay",),
        summary={
            "statistic": "largest |correlation| of z[t] with the leader's acceleration at t-k",
            "lag_steps": int(lags[worst]),
            "lag_s": float(lags[worst] * series.dt),
            "p_bonferroni_over_lags": p,
        },
        figure={"lags_s": lags * series.dt, "ccf": ccf, "band": 1.96 / np.sqrt(pairs)},
    )


def _time_in_window(t: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Each vehicle's time since its first scored step (vehicles have their own time axes)."""
    first = np.where(mask.any(axis=1), np.argmax(mask, axis=1), 0)
    return t - t[np.arange(t.shape[0]), first][:, None]


def covariate_checks(res: Residuals, series: FollowerArrays) -> list[Check]:
    """z^2 - 1 (variance) and z (mean) against speed, gap, relative speed and time in window."""
    covariates = {
        "speed": ("speed (m/s)", series.v),
        "gap": ("gap (m)", series.gap),
        "relative_speed": ("leader speed - speed (m/s)", series.lead_v - series.v),
        "time": ("time in the held-out window (s)", _time_in_window(series.t, res.mask)),
    }
    mask = res.mask
    checks = []
    for key, (label, values) in covariates.items():
        x = values[mask]
        for kind, y, causes in (
            (
                "variance",
                res.z[mask] ** 2 - 1.0,
                ("speed_dependent_noise",) if key == "speed" else (),
            ),
            ("mean", res.z[mask], ()),
        ):
            r = float(np.corrcoef(x, y)[0, 1]) if x.std() > 0 and y.std() > 0 else 0.0
            z = r * np.sqrt(x.size)
            edges = np.unique(np.quantile(x, np.linspace(0, 1, COVARIATE_BINS + 1)))
            which = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
            centres = np.array([x[which == b].mean() for b in range(len(edges) - 1)])
            means = np.array([y[which == b].mean() for b in range(len(edges) - 1)])
            ses = np.array(
                [
                    y[which == b].std() / np.sqrt(max(1, (which == b).sum()))
                    for b in range(len(edges) - 1)
                ]
            )
            checks.append(
                Check(
                    name=f"{kind}_vs_{key}",
                    title=f"Residual {kind} against {label}",
                    statistic=r,
                    p_value=float(2 * stats.norm.sf(abs(z))),
                    points_to=causes,
                    summary={
                        "statistic": f"correlation of {'z^2 - 1' if kind == 'variance' else 'z'} "
                        f"with {key}",
                        "z": float(z),
                        "p_positive": float(stats.norm.sf(z)),
                    },
                    figure={"label": label, "centres": centres, "means": means, "ses": ses},
                )
            )
    return checks


def long_run_sd(centred: np.ndarray) -> float:
    """The long-run standard deviation of a centred series: Bartlett weights up to the lag
    4 (n / 100)^(2/9) (Newey & West 1994), so short-range autocorrelation does not pass for a
    shift in the mean."""
    n = centred.size
    lags = int(4 * (n / 100) ** (2 / 9))
    variance = centred @ centred / n
    for lag in range(1, min(lags, n - 1) + 1):
        variance += 2 * (1 - lag / (lags + 1)) * (centred[lag:] @ centred[:-lag]) / n
    return float(np.sqrt(variance))


def _flagged_share(p_values: list[float]) -> tuple[np.ndarray, float, int, float]:
    """Per-vehicle p-values as an array, the share and number of vehicles flagged at 5%, and
    the binomial tail of that number: under the null each vehicle flags with probability 0.05,
    and vehicles are independent, so the tail is calibrated across vehicles."""
    p_values = np.asarray(p_values)
    flagged = int(np.sum(p_values < 0.05))
    share = flagged / p_values.size if p_values.size else 0.0
    p = float(stats.binom.sf(flagged - 1, p_values.size, 0.05)) if p_values.size else 1.0
    return p_values, share, flagged, p


def change_point_check(res: Residuals) -> Check:
    """Per-vehicle CUSUM of z: the share of vehicles whose mean shifts inside the window."""
    p_values, paths = [], []
    for z, used in zip(res.z, res.mask, strict=True):
        values = z[used]
        if values.size < 10:
            continue
        centred = values - values.mean()
        # Scaled by the long-run sd: under the null the bridge's sup then follows Kolmogorov's
        # law even where the one-step residuals are mildly autocorrelated (a continuous-time
        # driver seen through a one-step model is), which the autocorrelation checks judge.
        path = np.cumsum(centred) / (long_run_sd(centred) * np.sqrt(values.size))
        paths.append(path)
        p_values.append(float(stats.kstwobign.sf(np.abs(path).max())))
    p_values, share, flagged, p = _flagged_share(p_values)
    return Check(
        name="change_points",
        title="Change points in the residual mean (CUSUM per vehicle)",
        statistic=share,
        p_value=p,
        points_to=("drifting_parameters",),
        summary={
            "statistic": "share of vehicles with a CUSUM change point at the 5% level",
            "vehicles": int(p_values.size),
            "flagged": flagged,
        },
        figure={"paths": paths, "p_values": p_values},
        screening=True,
    )


def _block_gain_p_value(z: np.ndarray, acceleration: np.ndarray, block: int):
    """One vehicle's gains in consecutive blocks of ``block`` steps (the slope of z on the
    predicted acceleration through zero: a residual proportional to what the rule asks for)
    about their weighted mean, and the p-value of their equality: the F test of
    the gains' weighted spread, its error variance scaled by the long-run variance of the
    gain's score terms, so that the short-range autocorrelation of one-step residuals does not
    pass for a moving gain. None when fewer than two blocks ask for any acceleration."""
    count = z.size // block
    z_blocks = z[: count * block].reshape(count, block)
    a_blocks = acceleration[: count * block].reshape(count, block)
    weight = (a_blocks**2).sum(axis=1)
    keep = weight > 0
    if keep.sum() < 2:
        return None
    z_blocks, a_blocks, weight = z_blocks[keep], a_blocks[keep], weight[keep]
    count = int(keep.sum())
    gains = (z_blocks * a_blocks).sum(axis=1) / weight
    common = (gains * weight).sum() / weight.sum()
    errors = z_blocks - gains[:, None] * a_blocks
    dof = count * block - count  # one gain per block
    score_terms = (errors * a_blocks).ravel()
    inflation = long_run_sd(score_terms) ** 2 / (score_terms @ score_terms / score_terms.size)
    variance = (errors**2).sum() / dof * inflation
    spread = ((gains - common) ** 2 * weight).sum() / (count - 1)
    return gains - common, float(stats.f.sf(spread / variance, count - 1, dof))


def gain_drift_check(res: Residuals, dt: float) -> Check:
    """Does the strength of the rule change in time within a vehicle? (screening check)

    Per vehicle, over every step with a residual (the fitting window too: a drift is a change
    within the record, which the fitted parameters cannot absorb), the slope of z on the
    predicted acceleration in blocks of :data:`GAIN_BLOCK_S` (:func:`_block_gain_p_value`);
    the vehicles' p-values combined by Stouffer's method, with the share of vehicles whose
    slopes differ at the 5% level beside it.
    """
    block = round(GAIN_BLOCK_S / dt)
    p_values, paths = [], []
    for z, used, acceleration in zip(res.z, res.usable, res.acceleration, strict=True):
        found = _block_gain_p_value(z[used], acceleration[used], block)
        if found is None:
            continue
        paths.append(found[0])
        p_values.append(found[1])
    p_values, share, flagged, _ = _flagged_share(p_values)
    # Stouffer, not the count at 5%: a drift moves most vehicles' p-values part of the way, which
    # a count of vehicles significant on their own misses once blocks are long.
    clipped = np.clip(p_values, 1e-300, 1 - 1e-16)
    p = float(stats.combine_pvalues(clipped, method="stouffer")[1]) if p_values.size else 1.0
    return Check(
        name="gain_drift",
        title=f"A rule whose gain moves in time (slope of z on the predicted acceleration, "
        f"{GAIN_BLOCK_S:g} s blocks)",
        statistic=share,
        p_value=p,
        points_to=(),
        summary={
            "statistic": "share of vehicles whose block slopes differ at the 5% level",
            "p_value": "Stouffer's combination of the vehicles' p-values",
            "vehicles": int(p_values.size),
            "flagged": flagged,
            "block_s": GAIN_BLOCK_S,
        },
        figure={"slopes": paths, "p_values": p_values, "block_s": GAIN_BLOCK_S},
        screening=True,
    )


@functools.partial(jax.jit, static_argnums=(0, 3))
def _vehicle_scores(
    extended: ExtendedModel, base_theta: Array, steps: StepInputs, tested: int
) -> Array:
    """Efficient score of each vehicle's held-out log-likelihood in the extension's first
    ``tested`` parameters at their off values (module docstring: the slope with the
    execution-noise sd profiled out), averaged over draws: (vehicle, tested)."""
    model = extended.model
    names = model.param_names
    off = jnp.asarray([model.spec(n).default for n in extended.new_params], base_theta.dtype)
    noise = model.execution_noise_param
    noise_column = names.index(noise) if noise in names[: base_theta.shape[-1]] else None
    first = base_theta.shape[-1]

    def step_logliks(full, steps_v):
        return step_logpdfs(model, fill_params(model, names, full), steps_v)

    def per_draw(theta, steps_v):
        held = steps_v.heldout > 0
        if noise_column is None:
            slope_psi = jax.jacfwd(lambda psi: step_logliks(jnp.concatenate([theta, psi]), steps_v))
            return jnp.sum(jnp.where(held[:, None], slope_psi(off)[:, :tested], 0.0), axis=0)
        # One Jacobian in every parameter, so the likelihood is traced and compiled once.
        slopes = jax.jacfwd(step_logliks)(jnp.concatenate([theta, off]), steps_v)
        slope_psi = jnp.where(held[:, None], slopes[:, first : first + tested], 0.0)
        slope_sigma = jnp.where(held, slopes[:, noise_column], 0.0)
        # Regression of each psi-score on the sigma-score over steps (their information).
        beta = slope_sigma @ slope_psi / jnp.maximum(jnp.sum(slope_sigma**2), 1e-12)
        return jnp.sum(slope_psi, axis=0) - beta * jnp.sum(slope_sigma)

    def per_vehicle(theta_v, steps_v):
        return jax.vmap(lambda th: per_draw(th, steps_v))(theta_v).mean(axis=0)

    return jax.vmap(per_vehicle)(base_theta, steps)


def _off_inside(extended: ExtendedModel) -> bool:
    """Whether some parameter of the extension is switched off inside its bounds (so the
    extension can move either way from the base model)."""
    specs = [extended.model.spec(n) for n in extended.new_params]
    return any(s.lower < s.default < s.upper for s in specs)


def score_check(
    cause: str, fit: FitResult, series: FollowerArrays, *, num_draws: int = 16
) -> Check:
    """The score test of the ``cause`` extension against the fitted base model (module
    docstring): one-sided in its first parameter, or two-sided in all of them where their off
    values lie inside their bounds."""
    extended = extend(cause, fit.model.base)
    if extended.model.filter is not None or not extended.new_params:
        raise ValueError(f"no score test for {extended.name}")
    steps = step_inputs(series, extended.model)
    draws = np.linspace(0, fit.theta.shape[1] - 1, min(num_draws, fit.theta.shape[1])).astype(int)
    theta = jnp.asarray(fit.theta[:, draws], dtype=steps.v.dtype)
    if _off_inside(extended):
        return _vector_score_check(cause, extended, theta, steps)
    scores = np.asarray(_vehicle_scores(extended, theta, steps, 1)[:, 0], np.float64)
    scores = np.nan_to_num(scores)
    total = scores.sum()
    norm = np.sqrt(np.sum(scores**2))
    z = float(total / norm) if norm > 0 else 0.0
    return Check(
        name=f"score_{cause}",
        title=f"Score test: {extended.new_params[0]} (does {cause} improve held-out fit?)",
        statistic=z,
        p_value=float(stats.norm.sf(z)),
        points_to=(cause,),
        summary={
            "statistic": f"sum of per-vehicle held-out efficient score in "
            f"{extended.new_params[0]} at the extension's off values (the execution-noise sd "
            "profiled out) / root sum of squares",
            "parameter": extended.new_params[0],
            "vehicles_positive": int(np.sum(scores > 0)),
            "vehicles": int(scores.size),
        },
        figure={"scores": scores},
        screening=True,
    )


def _vector_score_check(
    cause: str, extended: ExtendedModel, theta: Array, steps: StepInputs
) -> Check:
    """The two-sided score test in every parameter of ``extended`` (module docstring): Hotelling's
    T^2 across vehicles; the statistic is its p-value as a one-sided normal quantile, so it reads
    on the one-parameter tests' scale."""
    params = extended.new_params
    scores = np.nan_to_num(
        np.asarray(_vehicle_scores(extended, theta, steps, len(params)), np.float64)
    )
    vehicles = scores.shape[0]
    mean = scores.mean(axis=0)
    # pinv: a parameter whose score is the same in every vehicle (a feature the data never
    # excite) carries no information and drops out instead of making the matrix singular.
    covariance = np.cov(scores, rowvar=False) if vehicles > 1 else np.zeros((len(params),) * 2)
    inverse = np.linalg.pinv(np.atleast_2d(covariance))
    rank = int(np.linalg.matrix_rank(np.atleast_2d(covariance)))
    t_squared = float(vehicles * mean @ inverse @ mean)
    if 0 < rank < vehicles:
        f = (vehicles - rank) / (rank * (vehicles - 1)) * t_squared
        p = float(stats.f.sf(f, rank, vehicles - rank))
    else:
        p = 1.0  # fewer vehicles than informative parameters: no evidence either way
    return Check(
        name=f"score_{cause}",
        title=f"Score test: {', '.join(params)} (does {cause} improve held-out fit?)",
        # Clipped so that p = 1 (no evidence) reads as a finite quantile, as JSON needs.
        statistic=float(stats.norm.isf(min(p, 1.0 - 1e-12))),
        p_value=p,
        points_to=(cause,),
        summary={
            "statistic": "one-sided normal quantile of the p-value of Hotelling's T^2 of the "
            f"vehicles' held-out efficient scores in {', '.join(params)} at the extension's off "
            "values (the execution-noise sd profiled out); F on (k, N - k) degrees of freedom, "
            "both directions",
            "t_squared": t_squared,
            "degrees_of_freedom": [rank, vehicles - rank],
            "per_vehicle": "vehicle's share of T^2",
            "vehicles": int(vehicles),
        },
        # Each vehicle's share of T^2: they sum to it.
        figure={"values": scores @ inverse @ mean},
        screening=True,
    )


def multistep_check(rollouts: Rollouts, dt: float) -> Check:
    """Closed-loop posterior predictive check: does the observed position stay inside the band?

    For every held-out window the observed position (offset 0) is ranked among the rollouts'
    simulated positions at each horizon step; a calibrated model covers it by its central 90%
    band 90% of the time. The number is the coverage at the end of the horizon.

    The p-value (screening: calibrated across vehicles) tests whether observations fall in the
    rollouts' tails more often than a calibrated forecast puts them there: per window, the
    distance of the end position's PIT from 1/2 minus its expectation when the observation is
    exchangeable with the n rollouts (the PIT then uniform on 0, 1/n, ..., 1), averaged over each
    vehicle's windows, one-sided t-test across vehicles (N - 1 df). An empirical 5-95% band of n
    rollouts covers less than 90% even for a calibrated model, so coverage itself is not tested.
    """
    offsets = rollouts.offset
    if offsets.shape[0] == 0:
        return Check(
            name="multistep",
            title="Closed-loop position band over held-out windows",
            statistic=float("nan"),
            p_value=None,
            points_to=(),
            summary={"statistic": "no complete held-out window", "windows": 0},
            figure={},
        )
    low, high = np.quantile(offsets, [0.05, 0.95], axis=1)
    covered = (low <= 0.0) & (high >= 0.0)
    coverage = covered.mean(axis=0)
    end = offsets[:, :, -1]
    # Ties (two stopped cars) count half: the mid-rank PIT.
    horizon_pit = (end < 0.0).mean(axis=1) + 0.5 * (end == 0.0).mean(axis=1)
    members = offsets.shape[1]
    exchangeable = np.abs(np.arange(members + 1) / members - 0.5).mean()
    excess = np.abs(horizon_pit - 0.5) - exchangeable
    rows = rollouts.windows.row
    per_vehicle = np.array([excess[rows == v].mean() for v in np.unique(rows)])
    t, p_tails, _ = _t_across_vehicles(per_vehicle)
    rmse = np.sqrt((offsets**2).mean(axis=(0, 1)))
    return Check(
        name="multistep",
        title="Closed-loop position band over held-out windows",
        statistic=float(coverage[-1]),
        p_value=p_tails,
        points_to=(),
        summary={
            "statistic": "share of windows whose observed end position lies in the central 90% "
            "band of the rollouts",
            "windows": int(offsets.shape[0]),
            "rollouts_per_window": int(members),
            "horizon_s": float(offsets.shape[2] * dt),
            "rmse_at_horizon_m": float(rmse[-1]),
            "rollout_collisions": int(rollouts.collisions.sum()),
            "p_value": "one-sided t-test across vehicles of the mean excess of |PIT - 1/2| at the "
            "horizon over its value for a calibrated forecast (observations too often in the tails)",
            "t": t,
            "vehicles": int(per_vehicle.size),
            "per_vehicle": "excess |PIT - 1/2| at the horizon",
        },
        figure={
            "time_s": np.arange(1, offsets.shape[2] + 1) * dt,
            "coverage": coverage,
            "rmse": rmse,
            "horizon_pit": horizon_pit,
            "example": offsets[0],
            "values": per_vehicle,
        },
        screening=True,
    )


def run_checks(
    key: Array,
    fit: FitResult,
    series: FollowerArrays,
    *,
    causes: tuple[str, ...],
) -> tuple[Residuals, list[Check]]:
    """Every check of the base fit ``fit`` on ``series`` (a :func:`~bayesdrive.data.views.scored_series`),
    with a score test for each of ``causes`` that scores steps on their own (the hidden-state ones
    rely on the residual checks)."""
    res = predictive_residuals(key, fit, step_inputs(series, fit.model.model))
    checks = [
        calibration_check(res),
        autocorrelation_check(res),
        *vehicle_autocorrelation_checks(res),
        *leader_cross_correlation_check(res, series),
        noise_speed_by_vehicle_check(res, series),
        *covariate_checks(res, series),
        change_point_check(res),
        gain_drift_check(res, series.dt),
        *(
            score_check(cause, fit, series)
            for cause in causes
            # A hidden-state model's slope at "off" is zero (a variance at its boundary).
            if extend(cause, fit.model.base).model.filter is None
        ),
    ]
    return res, checks
