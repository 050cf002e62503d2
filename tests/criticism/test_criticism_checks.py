"""The checks and the gain statistics on constructed inputs whose answers are known."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from bayesdrive.criticism.checks import (
    Residuals,
    autocorrelation_check,
    calibration_check,
    change_point_check,
    covariate_checks,
    gain_drift_check,
    leader_cross_correlation_check,
    noise_speed_by_vehicle_check,
    score_check,
    vehicle_autocorrelation_checks,
)
from bayesdrive.criticism.gain import elpd_gain, holm, rmse_change
from bayesdrive.data.views import AheadArrays, FollowerArrays, ScoredWindows, scored_series
from bayesdrive.drivers.extensions import as_extended
from bayesdrive.drivers.idm import IDM
from bayesdrive.inference.engines.heldout_evidence import FitResult
from tests.followers import corrected_follower

VEHICLES, STEPS = 12, 300


def residuals_from(z: np.ndarray, acceleration: np.ndarray | None = None) -> Residuals:
    every = np.ones(z.shape, bool)
    if acceleration is None:
        acceleration = np.zeros(z.shape)
    return Residuals(
        pit=stats.norm.cdf(z), z=z, mask=every, usable=every, acceleration=acceleration
    )


def ar1(rng, rho: float, count: int = VEHICLES) -> np.ndarray:
    z = np.empty((count, STEPS))
    z[:, 0] = rng.normal(size=count)
    for t in range(1, STEPS):
        z[:, t] = rho * z[:, t - 1] + np.sqrt(1 - rho**2) * rng.normal(size=count)
    return z


def series_with(lead_acc: np.ndarray, v: np.ndarray | None = None) -> FollowerArrays:
    ones = np.ones((VEHICLES, STEPS))
    return FollowerArrays(
        vehicle_ids=tuple(str(i) for i in range(VEHICLES)),
        t=np.tile(np.arange(STEPS) * 0.1, (VEHICLES, 1)),
        v=ones * 10 if v is None else v,
        next_v=ones * 10,
        dx=ones,
        gap=ones * 20,
        lead_v=ones * 10,
        has_leader=ones,
        mask=ones,
        dt=0.1,
        ahead=AheadArrays(
            lead_acc=lead_acc,
            gap2=ones * 40,
            lead2_v=ones * 10,
            has_leader2=ones,
            lead_age=ones * 100,
        ),
        windows=ScoredWindows(fit=0 * ones, heldout=ones),
    )


def test_autocorrelation_check_finds_ar1_and_passes_white_noise():
    """AR(1) rho = 0.5 residuals (seed 1, 3600 pairs): lag-1 estimate within 0.05 of 0.5, p tiny;
    white noise (seed 2): |lag 1| < 4 / sqrt(pairs) and p > 1e-3."""
    rng = np.random.default_rng(1)
    check = autocorrelation_check(residuals_from(ar1(rng, 0.5)))
    assert abs(check.statistic - 0.5) < 0.05
    assert check.summary["p_positive"] < 1e-12
    white = autocorrelation_check(
        residuals_from(np.random.default_rng(2).normal(size=(VEHICLES, STEPS)))
    )
    pairs = VEHICLES * (STEPS - 1)
    assert abs(white.statistic) < 4 / np.sqrt(pairs)
    assert white.p_value > 1e-3


def test_measurement_noise_signature_is_negative_lag_one():
    """Differences of white noise (an MA(1) with correlation -1/2) point to measurement noise,
    pooled and across vehicles; white noise does not (seeds 3, 10)."""
    noise = np.random.default_rng(3).normal(size=(VEHICLES, STEPS + 1))
    differenced = residuals_from(np.diff(noise, axis=1) / np.sqrt(2))
    check = autocorrelation_check(differenced)
    assert abs(check.statistic + 0.5) < 0.05
    assert check.summary["p_negative"] < 1e-12
    lag1, _ = vehicle_autocorrelation_checks(differenced)
    assert "measurement_noise" in lag1.points_to and lag1.summary["p_negative"] < 1e-6
    white = vehicle_autocorrelation_checks(
        residuals_from(np.random.default_rng(10).normal(size=(VEHICLES, STEPS)))
    )
    assert all(c.p_value > 1e-3 for c in white)


def test_drift_signature_is_a_long_lag_tail():
    """A slow random walk added to white residuals (seed 11) raises the lags 10-30 autocorrelation
    in every vehicle: the across-vehicle t-test (11 df) points to drifting parameters."""
    rng = np.random.default_rng(11)
    walk = np.cumsum(0.15 * rng.normal(size=(VEHICLES, STEPS)), axis=1)
    _, long_lag = vehicle_autocorrelation_checks(
        residuals_from(rng.normal(size=(VEHICLES, STEPS)) + walk)
    )
    assert long_lag.points_to == ("drifting_parameters",) and long_lag.p_value < 1e-3


def test_calibration_check_uniform_versus_overdispersed():
    """PIT of N(0, 1) data under N(0, 1) is uniform; under N(0, 1.5^2) data it is U-shaped:
    chi-square p < 1e-12 and the 90% interval covers < 0.85 (expected 0.73). Seeds 4, 5."""
    good = calibration_check(
        residuals_from(np.random.default_rng(4).normal(size=(VEHICLES, STEPS)))
    )
    assert good.p_value > 1e-3
    assert abs(good.summary["coverage_90"] - 0.9) < 0.02
    wide = 1.5 * np.random.default_rng(5).normal(size=(VEHICLES, STEPS))
    bad = calibration_check(residuals_from(wide))
    assert bad.p_value < 1e-12
    assert bad.summary["coverage_90"] < 0.85


def test_leader_cross_correlation_finds_the_lag():
    """Residuals that respond to the leader's acceleration 0.7 s (7 steps) earlier."""
    rng = np.random.default_rng(6)
    lead_acc = rng.normal(size=(VEHICLES, STEPS))
    z = rng.normal(size=(VEHICLES, STEPS))
    z[:, 7:] += 0.5 * lead_acc[:, :-7]
    by_vehicle, check = leader_cross_correlation_check(
        residuals_from(z / np.sqrt(1.25)), series_with(lead_acc)
    )
    assert check.summary["lag_steps"] == 7
    assert check.p_value < 1e-12
    assert by_vehicle.p_value < 1e-6
    unrelated_by_vehicle, unrelated = leader_cross_correlation_check(
        residuals_from(rng.normal(size=(VEHICLES, STEPS))), series_with(lead_acc)
    )
    assert unrelated.p_value > 1e-3
    assert unrelated_by_vehicle.p_value > 1e-3


def test_variance_against_speed():
    """Residual sd growing with speed (sd 1 + 0.1 (v - 10), speeds 2-18 m/s) shows in the
    variance-vs-speed check (one-sided p < 1e-12) but not in the mean-vs-speed check."""
    rng = np.random.default_rng(7)
    speed = rng.uniform(2, 18, size=(VEHICLES, STEPS))
    z = rng.normal(size=(VEHICLES, STEPS)) * (1 + 0.1 * (speed - 10))
    checks = {c.name: c for c in covariate_checks(residuals_from(z), series_with(0 * z, v=speed))}
    assert checks["variance_vs_speed"].summary["p_positive"] < 1e-12
    assert checks["mean_vs_speed"].p_value > 1e-3


def test_noise_growing_with_speed_within_vehicles_screens_and_levels_do_not_matter():
    """Each vehicle drives in its own narrow speed band (5-25 m/s apart) and has its own noise
    level, unrelated to its speed (numpy, seed 11). Within a vehicle the sd grows with speed
    (1 + 0.3 (v - band centre)): the per-vehicle rank check screens it in (p < 1e-4), while the
    pooled variance-vs-speed correlation, mixing the levels, does not see it (p_positive > 0.05).
    White residuals (the negative control) and sds falling with speed do not screen in
    (p > 0.05); scaling one vehicle's residuals changes nothing (ranks)."""
    rng = np.random.default_rng(11)
    centre = rng.permutation(np.linspace(5, 25, VEHICLES))[:, None]
    speed = centre + rng.uniform(-2, 2, size=(VEHICLES, STEPS))
    level = np.linspace(3.0, 0.5, VEHICLES)[np.argsort(np.argsort(centre[:, 0]))][:, None]
    white = rng.normal(size=(VEHICLES, STEPS))
    growing = white * level * (1 + 0.3 * (speed - centre))
    series = series_with(0 * white, v=speed)
    found = noise_speed_by_vehicle_check(residuals_from(growing), series)
    assert found.screening and found.points_to == ("speed_dependent_noise",)
    assert found.p_value < 1e-4 and found.summary["vehicles"] == VEHICLES
    pooled = {c.name: c for c in covariate_checks(residuals_from(growing), series)}
    assert pooled["variance_vs_speed"].summary["p_positive"] > 0.05
    assert noise_speed_by_vehicle_check(residuals_from(white * level), series).p_value > 0.05
    falling = white * level * (1 - 0.3 * (speed - centre))
    assert noise_speed_by_vehicle_check(residuals_from(falling), series).p_value > 0.05
    rescaled = growing.copy()
    rescaled[0] *= 5.0
    again = noise_speed_by_vehicle_check(residuals_from(rescaled), series)
    assert again.statistic == pytest.approx(found.statistic)


def test_change_points():
    """A mean shift of 1 sd halfway through every vehicle's window flags nearly all vehicles;
    white noise flags about 5% (binomial tail p > 1e-3). Seeds 8, 9."""
    shifted = np.random.default_rng(8).normal(size=(VEHICLES, STEPS))
    shifted[:, STEPS // 2 :] += 1.0
    assert change_point_check(residuals_from(shifted)).p_value < 1e-12
    white = change_point_check(
        residuals_from(np.random.default_rng(9).normal(size=(VEHICLES, STEPS)))
    )
    assert white.p_value > 1e-3


def test_change_points_are_not_short_range_autocorrelation():
    """AR(1) residuals (rho 0.3) without a shift flag about 5% of vehicles once the CUSUM is scaled
    by the long-run sd; scaled by the one-step sd they flag many. A shift on top is still found.
    Seed 10; 40 vehicles."""
    z = ar1(np.random.default_rng(10), 0.3, count=40)
    scaled = change_point_check(residuals_from(z))
    assert scaled.p_value > 1e-3 and scaled.summary["flagged"] <= 6
    one_step = [
        stats.kstwobign.sf(np.abs(np.cumsum(r - r.mean()) / (r.std() * np.sqrt(STEPS))).max())
        for r in z
    ]
    assert np.mean(np.asarray(one_step) < 0.05) > 0.1
    shifted = z.copy()
    shifted[:, STEPS // 2 :] += 1.0
    assert change_point_check(residuals_from(shifted)).p_value < 1e-12


def smooth_accelerations(rng, count: int) -> np.ndarray:
    """Predicted accelerations as a driver's are: smooth (AR(1), rho 0.98 per 0.1 s step), sd
    about 0.5 m/s^2, changing sign now and then."""
    return 0.5 * ar1(rng, 0.98, count)


def test_gain_drift_finds_a_rule_whose_strength_swings_and_not_a_fixed_one():
    """z = (g(t) - 1) a / 0.3 + white noise, a the predicted acceleration and the gain g swinging
    by 40% with a 25 s period (as a drifting a_max scales the rule): nearly every vehicle is
    flagged (p < 1e-6). Negative controls, each with at most 3 of 12 vehicles flagged and
    p > 1e-3: the same residual with a gain fixed at 1.4 (a wrong but constant strength), white
    noise, and AR(1) noise (rho 0.3, short-range, unrelated to a). Seeds 11-14; 30 s at 10 Hz."""
    rng = np.random.default_rng(11)
    acceleration = smooth_accelerations(rng, VEHICLES)
    t = np.arange(STEPS) * 0.1
    phase = rng.uniform(0, 2 * np.pi, (VEHICLES, 1))
    swing = 0.4 * np.sin(2 * np.pi * t / 25.0 + phase)
    white = np.random.default_rng(12).normal(size=(VEHICLES, STEPS))
    found = gain_drift_check(residuals_from(swing * acceleration / 0.3 + white, acceleration), 0.1)
    assert found.p_value < 1e-6 and found.summary["flagged"] >= VEHICLES - 2
    assert found.points_to == () and found.screening
    for z in (
        0.4 * acceleration / 0.3 + white,
        np.random.default_rng(13).normal(size=(VEHICLES, STEPS)),
        ar1(np.random.default_rng(14), 0.3),
    ):
        quiet = gain_drift_check(residuals_from(z, acceleration), 0.1)
        assert quiet.p_value > 1e-3 and quiet.summary["flagged"] <= 3


def fit_with(log_z_held, theta=None) -> FitResult:
    n = len(log_z_held)
    zeros = np.zeros(n)
    return FitResult(
        model=as_extended(IDM),
        names=IDM.param_names,
        theta=np.zeros((n, 2, 6)) if theta is None else theta,
        log_z_fit=zeros,
        log_z_held=np.asarray(log_z_held, float),
        stages_fit=zeros,
        stages_held=zeros,
        from_prior=np.ones(n, bool),
        acceptance=zeros,
        compile_time_s=0.0,
        run_time_s=0.0,
    )


def test_gain_standard_error_is_across_vehicles():
    """Per-vehicle gains 1, 2, 3, 4: total 10, se = sqrt(4) * sd = 2 * 1.2910 = 2.582, t = 3.873;
    the decision uses log(1 + g) = log 2, log 3, log 4, log 5 against Student t with 3 df."""
    gain = elpd_gain(fit_with([10.0, 20.0, 30.0, 40.0]), fit_with([11.0, 22.0, 33.0, 44.0]))
    assert gain.elpd == pytest.approx(10.0)
    assert gain.se == pytest.approx(2 * np.std([1, 2, 3, 4], ddof=1))
    assert gain.t == pytest.approx(10.0 / gain.se)
    h = np.log([2.0, 3.0, 4.0, 5.0])
    assert gain.t_transformed == pytest.approx(h.mean() / (h.std(ddof=1) / 2))
    assert gain.p_value == pytest.approx(stats.t.sf(gain.t_transformed, df=3))


def test_one_huge_vehicle_does_not_hide_an_effect_every_vehicle_shows():
    """Gains 200..270 in seven vehicles and 20 000 in one: G/se is about 1 (the outlier sets mean
    and sd alike), while the transformed test rejects at the Holm level for 7 causes."""
    gains = np.array([200.0, 210, 220, 230, 240, 250, 270, 20_000])
    gain = elpd_gain(fit_with(np.zeros(8)), fit_with(gains))
    assert gain.t < 1.5
    assert gain.p_value < 0.05 / 7


def test_null_like_gains_are_not_significant():
    """Small losses in most vehicles and small gains in a few: p > 0.5."""
    gain = elpd_gain(
        fit_with(np.zeros(8)), fit_with([-1.2, -0.4, -2.0, 0.6, -0.8, 0.3, -1.5, -0.1])
    )
    assert gain.p_value > 0.5


def test_a_non_finite_extension_is_never_significant_and_a_broken_base_is_an_error():
    gain = elpd_gain(fit_with([1.0, 2.0, 3.0]), fit_with([5.0, -np.inf, 9.0]))
    assert gain.p_value == 1.0 and np.isnan(gain.elpd)
    with pytest.raises(FloatingPointError, match="vehicle rows \\[1\\]"):
        elpd_gain(fit_with([1.0, np.nan]), fit_with([1.0, 2.0]))


def test_holm_by_hand():
    """Family of 4, alpha 0.05: 0.01 <= 0.0125 rejected; 0.02 > 0.05/3 stops the procedure.
    A member without a p-value counts as 1, so screening never adds rejections."""
    p = {"a": 0.01, "b": 0.02, "c": 0.04}
    assert holm(p, ["a", "b", "c", "d"]) == {"a"}
    assert holm(p, ["a", "b", "c"]) == {"a", "b", "c"}  # 0.01<=0.0167, 0.02<=0.025, 0.04<=0.05
    assert holm({}, ["a", "b"]) == set()


def test_rmse_change_mean_and_se():
    change, se = rmse_change(np.array([1.0, 2.0, np.nan]), np.array([0.5, 1.0, 3.0]))
    assert change == pytest.approx(-0.75)
    assert se == pytest.approx(np.std([-0.5, -1.0], ddof=1) / np.sqrt(2))


# The numpy follower's IDM values (tests/followers.py) and its noise sd.
FOLLOWER_TRUTH = {
    "v_des": 30.0,
    "d_min": 2.0,
    "tau": 1.0,
    "a_max": 3.0,
    "b_pref": 2.0,
    "sigma": 0.3,
}


@pytest.mark.parametrize(("hidden", "found"), [(-0.6, True), (0.6, True), (0.0, False)])
def test_the_state_corrections_score_test_is_two_sided_in_its_three_coefficients(hidden, found):
    """8 numpy followers of 60 s (tests/followers.py, seeds 31-38, fixed before the test ran) hide
    a correction of -0.6 or +0.6 m/s^2 on the closing feature, or none. Scored at the generator's
    IDM values, the state correction's score test (three coefficients, both directions) finds
    either sign with p < 1e-3; a one-sided test would miss one of them. Negative control: on the
    followers without the correction p > 0.01 (a 1% false alarm at this seed)."""
    series = scored_series(corrected_follower(hidden, seed=31, steps=600, pairs=8))
    vehicles = len(series.vehicle_ids)
    truth = np.asarray([FOLLOWER_TRUTH[name] for name in IDM.param_names])
    fit = fit_with(np.zeros(vehicles), theta=np.tile(truth, (vehicles, 2, 1)))
    check = score_check("state_correction", fit, series)
    assert check.screening and check.points_to == ("state_correction",)
    assert check.summary["degrees_of_freedom"] == [3, 5] and vehicles == 8
    assert check.summary["t_squared"] == pytest.approx(check.figure["values"].sum(), rel=1e-6)
    if found:
        assert check.p_value < 1e-3, check.summary
    else:
        assert check.p_value > 0.01, check.summary
