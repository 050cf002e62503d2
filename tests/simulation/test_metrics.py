"""Metrics against values computed by hand on tiny arrays."""

import json

import numpy as np
import pytest

from bayesdrive.simulation.metrics import (
    Observed,
    collision_onsets,
    distribution_distance,
    distribution_samples,
    kde,
    minimum_ttc,
    realised_jerk,
    rmse_by_step,
    scenario_metrics,
    speed_density,
    summarize,
)
from bayesdrive.simulation.rollout import Rollout


def test_rmse_is_the_root_of_the_mean_square_over_rollouts_and_vehicles():
    # Step 1 errors over (rollout, vehicle): 1, 3, -1, 1 -> mean square 12 / 4 = 3.
    simulated = np.array([[[0.0, 1.0], [0.0, 3.0]], [[0.0, -1.0], [0.0, 1.0]]])
    observed = np.zeros((2, 2))
    np.testing.assert_allclose(rmse_by_step(simulated, observed), [0.0, np.sqrt(3.0)])
    # Not the mean absolute error (1.5) nor the RMS of per-vehicle means.
    assert rmse_by_step(simulated, observed)[1] != pytest.approx(1.5)


def test_a_collision_lasting_several_steps_is_one_event():
    assert collision_onsets(np.array([[False, True, True, False, True]])) == 2
    assert collision_onsets(np.array([[True, True], [False, False]])) == 1
    assert collision_onsets(np.zeros((3, 2, 4), bool)) == 0


def tiny_scenario():
    """2 rollouts x 2 vehicles x 3 steps, the second vehicle of rollout 1 colliding twice."""
    x = np.array(
        [
            [[0.0, 1.0, 2.0, 3.0], [-10.0, -9.0, -8.0, -7.0]],
            [[0.0, 1.0, 2.0, 5.0], [-10.0, -9.0, -8.0, -3.0]],
        ]
    )
    v = np.full((2, 2, 4), 10.0)
    collision = np.zeros((2, 2, 3), bool)
    collision[1, 1] = [True, False, True]
    hard = np.zeros((2, 2, 3), bool)
    hard[0, 0, 2] = hard[1, 0, 0] = hard[1, 1, 1] = True
    rollout = Rollout(
        x=x,
        v=v,
        gap=np.full((2, 2, 4), 5.0),
        dx=np.diff(x, axis=-1),
        collision=collision,
        hard_braking=hard,
        off_road=np.zeros((2, 2, 3), bool),
    )
    observed = Observed(
        x=np.array([[0.0, 1.0, 2.0, 3.0], [-10.0, -9.0, -8.0, -7.0]]),
        # Vehicle 1 brakes at -4, -6, -2 m/s^2: two steps at or below -3.
        v=np.array([[10.0, 10.0, 10.0, 10.0], [10.0, 9.6, 9.0, 8.8]]),
        gap=np.array([[5.0, 5.0, 5.0, 5.0], [np.nan, 5.0, 5.0, 5.0]]),
        step_mask=np.ones(3),
        dt=0.1,
    )
    return rollout, observed


def test_scenario_metrics_by_hand():
    rollout, observed = tiny_scenario()
    m = scenario_metrics("tiny", rollout, observed)
    # Last-step position errors: 0, 0, 2, 4 -> RMSE sqrt(20 / 4), MAE 6 / 4.
    np.testing.assert_allclose(m.rmse_position_by_step, [0.0, 0.0, 0.0, np.sqrt(5.0)])
    assert m.mae_position_last == pytest.approx(1.5)
    # Speed errors at the last step: 0, 10 - 8.8 = 1.2 for both rollouts' vehicle 1.
    assert m.rmse_speed_by_step[-1] == pytest.approx(np.sqrt(2 * 1.2**2 / 4))
    assert m.mae_speed_last == pytest.approx(2 * 1.2 / 4)
    assert m.collisions == 2
    assert m.collided == 1  # one vehicle-rollout of four
    assert m.hard_braking == 3
    assert m.data_hard_braking == 2
    assert m.off_road == 0
    # Vehicle-rollouts with a first event at steps 1 (two of them) and 3; one never has any.
    np.testing.assert_allclose(m.undesirable_by_step, [0.0, 0.5, 0.5, 0.75])
    # CRPS of two members {a, b} at 0: (|a| + |b|) / 2 - |a - b| / 4; position {0, 2} and
    # {0, 4}: 0.5 and 1; speed {0, 0} and {1.2, 1.2}: 0 and 1.2.
    assert m.crps_position_last == pytest.approx(0.75)
    assert m.crps_speed_last == pytest.approx(0.6)
    # Equal members: the energy score is the norm of the path error; gaps are exact, vehicle 1's
    # speed errors are 0.4, 1.0, 1.2 (m/s, in the 1 m/s unit).
    assert m.energy_score_path == pytest.approx(np.sqrt(0.4**2 + 1.0 + 1.2**2) / 2)
    # The predictive mean's last-step position errors: (0 + 2) / 2 and (0 + 4) / 2.
    assert m.predictive_mean_sq_error_last == pytest.approx((1.0**2 + 2.0**2) / 2)
    # Vehicle 0 ends at its observed position in rollout 0 and ahead of it in rollout 1: no
    # member behind, one tie, so the observation's rank among 3 values is 0 or 1, mid-rank
    # (0 + 0.5 * 2) / 3; vehicle 1 likewise.
    np.testing.assert_allclose(m.pit_position_last, [1 / 3, 1 / 3])


def test_steps_past_the_end_of_a_scene_are_not_scored():
    rollout, observed = tiny_scenario()
    short = observed._replace(step_mask=np.array([1.0, 1.0, 0.0]))
    m = scenario_metrics("short", rollout, short)
    assert np.isnan(m.rmse_position_by_step[3])
    assert m.last_step == 2
    assert m.mae_position_last == 0.0
    assert np.isnan(m.undesirable_by_step[3])
    # The data's third step (-2 m/s^2) would not count anyway; its second (-6) still does.
    assert m.data_hard_braking == 2
    samples = distribution_samples(rollout, short)
    assert len(samples.simulated_speed) == 2 * 2 * 2  # rollouts x vehicles x real steps 1..2
    assert len(samples.observed_speed) == 2 * 2


def test_distribution_samples_skip_steps_without_a_leader():
    rollout, observed = tiny_scenario()
    samples = distribution_samples(rollout, observed)
    # Observed gaps: vehicle 0 has 3 real steps, vehicle 1 has 3 (its NaN is at step 0).
    assert len(samples.observed_gap) == 6
    assert len(samples.simulated_gap) == 2 * 6
    gapless = observed._replace(gap=np.where(np.arange(4) == 2, np.nan, observed.gap))
    assert len(distribution_samples(rollout, gapless).observed_gap) == 4


def test_summary_across_scenarios_by_hand():
    rollout, observed = tiny_scenario()
    first = scenario_metrics("a", rollout, observed)
    exact = rollout._replace(
        x=np.broadcast_to(observed.x, (2, 2, 4)), collision=np.zeros((2, 2, 3), bool)
    )
    second = scenario_metrics("b", exact, observed)
    samples = [distribution_samples(rollout, observed), distribution_samples(exact, observed)]
    summary = summarize([first, second], samples)
    # Final position RMSE: sqrt(5) and 0 -> mean sqrt(5)/2, sample sd sqrt(5)/sqrt(2).
    assert summary["rmse_position_m"]["mean"] == pytest.approx(np.sqrt(5.0) / 2)
    assert summary["rmse_position_m"]["sd"] == pytest.approx(np.sqrt(5.0) / np.sqrt(2.0))
    assert summary["rmse_position_m"]["by_step"]["mean"][-1] == pytest.approx(np.sqrt(5.0) / 2)
    assert summary["collisions"] == {"total": 2, "per_rollout": 1.0, "fraction": 1 / 8}
    assert summary["hard_braking"] == {"total": 6, "per_rollout": 3.0, "data_total": 4}
    assert summary["scenarios"] == 2 and summary["vehicles"] == 4 and summary["rollouts"] == 2
    json.dumps(summary, allow_nan=False)  # JSON-ready: no NaN, no numpy types


def test_a_single_scenario_has_no_sd():
    rollout, observed = tiny_scenario()
    one = summarize(
        [scenario_metrics("a", rollout, observed)], [distribution_samples(rollout, observed)]
    )
    assert one["rmse_position_m"]["sd"] is None
    json.dumps(one, allow_nan=False)


def test_distribution_distances_by_hand():
    far = distribution_distance(np.zeros(3), np.ones(2))
    assert far == {"wasserstein": pytest.approx(1.0), "ks": pytest.approx(1.0)}
    # Half the mass moved by 2: W1 = 1; the CDFs differ by at most 1/2 between 0 and 2.
    half = distribution_distance(np.array([0.0, 2.0]), np.array([0.0, 0.0]))
    assert half == {"wasserstein": pytest.approx(1.0), "ks": pytest.approx(0.5)}
    assert distribution_distance(np.arange(5.0), np.arange(5.0)) == {"wasserstein": 0.0, "ks": 0.0}
    with pytest.raises(ValueError, match="empty"):
        distribution_distance(np.array([]), np.ones(2))


def test_kde_is_a_density_centred_on_the_samples():
    samples = np.random.default_rng(0).normal(3.0, 1.0, 500)
    grid = np.linspace(-5.0, 11.0, 1601)
    density = kde(samples, grid)
    assert np.trapezoid(density, grid) == pytest.approx(1.0, abs=1e-3)
    assert abs(grid[np.argmax(density)] - 3.0) < 0.3  # mode of N(3, 1) from 500 draws, seed 0


def test_speed_density_is_a_density_on_a_shared_grid():
    rng = np.random.default_rng(3)
    simulated, observed = rng.normal(20.0, 2.0, 200_000), rng.normal(15.0, 1.0, 500)
    density = speed_density(simulated, observed)
    grid = np.array(density["grid_mps"])
    for name, centre in (("simulated", 20.0), ("observed", 15.0)):
        values = np.array(density[name])
        assert np.trapezoid(values, grid) == pytest.approx(1.0, abs=0.02)
        assert grid[np.argmax(values)] == pytest.approx(centre, abs=0.5)


def test_speed_density_of_one_repeated_speed_is_a_narrow_peak():
    density = speed_density(np.full(100, 10.0), np.array([9.0, 10.0, 11.0]))
    grid, values = np.array(density["grid_mps"]), np.array(density["simulated"])
    assert np.trapezoid(values, grid) == pytest.approx(1.0, abs=0.01)
    assert grid[np.argmax(values)] == pytest.approx(10.0, abs=grid[1] - grid[0])


def test_jerk_is_the_change_of_the_realised_acceleration():
    # Accelerations over steps of 0.5 s: 2, 4, 6 m/s^2, so the jerk is 4 m/s^3 twice.
    np.testing.assert_allclose(realised_jerk(np.array([0.0, 1.0, 3.0, 6.0]), 0.5), [4.0, 4.0])


def test_minimum_ttc_reads_the_closing_speed_from_the_gap():
    # Closing at 2 m/s from 10 m (5 s), at 1 m/s from 8 m (8 s), then opening.
    gaps = np.array([[10.0, 8.0, 7.0, 7.5], [5.0, 6.0, 7.0, 8.0], [np.nan] * 4])
    np.testing.assert_allclose(minimum_ttc(gaps, 1.0), [5.0, np.inf, np.inf])


def test_interval_coverage_is_nominal_for_a_calibrated_forecast_and_not_for_an_overconfident_one():
    """Rollouts and observations drawn here with numpy, not by the simulator: a forecast whose
    rollouts share the observation's distribution covers at the nominal rates; one whose spread is
    half the observation's covers far less (the negative control). Seed 20261129; 400 scenarios of
    2 vehicles, 200 rollouts: the coverage's binomial sd is about 0.011 at 90%, the tolerance
    0.04."""
    rng = np.random.default_rng(20261129)
    _, observed = tiny_scenario()

    def coverage(spread: float) -> dict:
        metrics, samples = [], []
        for _ in range(400):
            end = observed.x[None, :, -1] + spread * rng.standard_normal((200, 2))
            end -= rng.standard_normal(2)  # the observation's own draw, sd 1
            x = np.broadcast_to(observed.x, (200, 2, 4)).copy()
            x[:, :, -1] = end
            rollout = Rollout(
                x=x,
                v=np.full((200, 2, 4), 10.0),
                gap=np.full((200, 2, 4), 5.0),
                dx=np.diff(x, axis=-1),
                collision=np.zeros((200, 2, 3), bool),
                hard_braking=np.zeros((200, 2, 3), bool),
                off_road=np.zeros((200, 2, 3), bool),
            )
            metrics.append(scenario_metrics("s", rollout, observed))
            samples.append(distribution_samples(rollout, observed))
        return summarize(metrics, samples)["calibration_position"]

    calibrated, overconfident = coverage(1.0), coverage(0.5)
    assert calibrated["windows"] == 800
    assert calibrated["coverage_50"] == pytest.approx(0.5, abs=0.04)
    assert calibrated["coverage_90"] == pytest.approx(0.9, abs=0.04)
    # Half the spread: the 90% interval is +-0.82 sd of the observation, which it covers 59%.
    assert overconfident["coverage_90"] < 0.7
    counts = overconfident["pit_counts"]
    assert counts[0] + counts[-1] > 0.3 * 800


def test_the_rank_pit_of_an_exchangeable_observation_is_uniform_and_covers_at_nominal_rates():
    """Observations drawn from the same law as the ensemble (numpy's generator, seed 39): the
    randomised rank PIT covers 0.50 and 0.90, within 4 standard errors of a binomial share over
    40,000 windows (0.010 and 0.006), with continuous and with tie-heavy (Poisson) members; the
    mid-rank of a 100-member ensemble covers 91 of its 101 ranks. Negative controls: the share of
    members below the observation (the PIT before this definition) covers too little and fails
    the histogram's chi-square; an ensemble 20% too narrow covers under 0.85."""
    from bayesdrive.simulation.calibration import pit_of_observation, pit_summary

    rng = np.random.default_rng(39)
    windows, members = 40_000, 100
    tolerance = {50: 4 * np.sqrt(0.25 / windows), 90: 4 * np.sqrt(0.09 / windows)}
    ties = rng.uniform(size=windows)
    continuous = rng.normal(size=(windows, members)) - rng.normal(size=(windows, 1))
    counts = rng.poisson(3.0, (windows, members)) - rng.poisson(3.0, (windows, 1))
    for errors in (continuous, counts.astype(float)):
        summary = pit_summary(pit_of_observation(errors, ties))
        for level in (50, 90):
            assert abs(summary[f"coverage_{level}"] - level / 100) < tolerance[level]
        assert summary["pit_chi2_p"] > 1e-3
    mid_rank = pit_summary(pit_of_observation(continuous, 0.5))
    assert abs(mid_rank["coverage_90"] - 91 / 101) < tolerance[90]

    share_below = pit_summary((continuous < 0.0).mean(axis=1))
    assert share_below["coverage_90"] < 0.9 - tolerance[90] and share_below["pit_chi2_p"] < 1e-6
    narrow = 0.8 * rng.normal(size=(windows, members)) - rng.normal(size=(windows, 1))
    assert pit_summary(pit_of_observation(narrow, ties))["coverage_90"] < 0.85
