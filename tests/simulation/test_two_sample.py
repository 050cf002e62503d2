"""The classifier two-sample tests: chance on identical distributions, power on different ones."""

import numpy as np
import pytest

import trafficgen
from bayesdrive.data import registry
from bayesdrive.simulation import two_sample
from bayesdrive.simulation.scenarios import platoon_scenarios
from bayesdrive.simulation.two_sample import (
    TRAJECTORY_FEATURE_NAMES,
    _cluster_interval,
    boosted_two_sample_test,
    classifier_two_sample_test,
    grouped_folds,
    permuted_labellings,
    segment_features,
    trajectory_features,
)


def test_null_rejections_stay_at_the_nominal_rate():
    # 20 null data sets (seeds 0-19, 100 + 100 rows from one distribution), 99 permutations each.
    # At the 5% level we expect 1 rejection; 5 or more has probability 0.003 if calibrated.
    rejections = 0
    for seed in range(20):
        rng = np.random.default_rng(seed)
        real, generated = rng.normal(size=(100, 6)), rng.normal(size=(100, 6))
        result = classifier_two_sample_test(real, generated, seed=seed, permutations=99)
        rejections += result.p_value < 0.05
    assert rejections <= 4


def test_shifted_distribution_is_detected():
    # A shift of 1 sd in one feature of six (expected accuracy about 0.69): the test must reject chance at 1%.
    rng = np.random.default_rng(2)
    real = rng.normal(size=(200, 6))
    generated = rng.normal(size=(200, 6))
    generated[:, 3] += 1.0
    result = classifier_two_sample_test(real, generated, seed=3, permutations=99)
    assert result.accuracy > 0.55 and result.p_value <= 0.01  # 0.01 = 1/(1+99), the floor


def test_same_seed_same_result():
    rng = np.random.default_rng(4)
    real, generated = rng.normal(size=(50, 3)), rng.normal(size=(60, 3)) + 0.2
    assert classifier_two_sample_test(real, generated, seed=5) == classifier_two_sample_test(
        real, generated, seed=5
    )


def test_segment_features_by_hand():
    speed = np.array([[10.0, 11.0, 13.0]])
    gap = np.array([[20.0, 18.0, 19.0]])
    features = segment_features(speed, gap, dt=1.0)
    # accelerations 1, 2 -> sd 0.5; one jerk value (1) -> sd 0
    np.testing.assert_allclose(features[0], [34 / 3, np.std([10, 11, 13]), 19.0, 18.0, 0.5, 0.0])


# The boosted classifier: gradient-boosted trees on per-step distributions, folds by vehicle.


def test_trajectory_features_by_hand():
    # Row 0: accelerations 1, 2, -1; jerks 1, -3; relative speeds 1, 0, -2, -1; closing speeds at
    # the start of each step -1, 0, 2. Row 1: stopped 20 m behind a stopped leader.
    speed = np.array([[10.0, 11.0, 13.0, 12.0], [0.0, 0.0, 0.0, 0.0]])
    gap = np.array([[20.0, 18.0, 19.0, 21.0], [20.0, 20.0, 20.0, 20.0]])
    lead = np.array([[11.0, 11.0, 11.0, 11.0], [0.0, 0.0, 0.0, 0.0]])
    features = dict(
        zip(TRAJECTORY_FEATURE_NAMES, trajectory_features(speed, gap, lead, dt=1.0).T, strict=True)
    )
    assert len(features) == len(TRAJECTORY_FEATURE_NAMES)
    np.testing.assert_allclose(features["speed_q50"], [11.5, 0.0])
    np.testing.assert_allclose(features["gap_q05"], [18.15, 20.0])
    np.testing.assert_allclose(features["accel_q50"], [1.0, 0.0])
    np.testing.assert_allclose(features["jerk_q50"], [-1.0, 0.0])
    np.testing.assert_allclose(features["relative_speed_q50"], [-0.5, 0.0])
    # gap / speed: 2 s at the first sample; the stopped car's headway is capped at 10 s.
    np.testing.assert_allclose(features["time_headway_q95"][1], 10.0)
    np.testing.assert_allclose(features["time_headway_q95"][0], 2 - 0.15 * (2 - 21 / 12))
    np.testing.assert_allclose(features["accel_sd"], [np.std([1, 2, -1]), 0.0])
    # Two lag-1 pairs, (1, 2) and (2, -1): correlation -1. One sign change in two.
    np.testing.assert_allclose(features["accel_autocorr"][0], -1.0)
    np.testing.assert_allclose(features["accel_sign_changes"], [0.5, 0.0])
    np.testing.assert_allclose(features["accel_closing_speed_corr"][0], -11 / 14)
    # A constant acceleration has no correlation with anything: missing, not 0.
    assert np.isnan(features["accel_autocorr"][1]) and np.isnan(
        features["accel_closing_speed_corr"][1]
    )


def test_permutations_keep_what_the_null_makes_exchangeable():
    rng = np.random.default_rng(8)
    # Vehicles a and b have real and generated segments (shuffled within each), c, d, e one kind
    # each (their labels move as wholes).
    groups = np.array(["a", "a", "a", "b", "b", "c", "c", "d", "e", "e", "e"])
    labels = np.array([0, 1, 1, 0, 1, 0, 0, 1, 1, 1, 1])
    drawn = permuted_labellings(rng, labels, groups, 200)
    for group in "ab":
        rows = groups == group
        assert np.all(drawn[:, rows].sum(axis=1) == labels[rows].sum())
    whole = [groups == group for group in "cde"]
    assert all(np.all(drawn[:, rows] == drawn[:, rows][:, :1]) for rows in whole)
    assert np.all(sum(drawn[:, rows][:, 0] for rows in whole) == 2)
    # They do move: each of c, d, e is the generated-free vehicle in some draw.
    assert all(np.any(drawn[:, rows][:, 0] == 0) for rows in whole)


def wilson_by_hand(p, n, z=1.96):
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return [centre - half, centre + half]


def test_the_interval_counts_a_vehicles_segments_as_fewer_trials():
    # Five vehicles of four segments, 16 of 20 right, per-vehicle hits 4, 3, 4, 2, 3: deviations
    # from 3.2 of 0.8, -0.2, 0.8, -1.2, -0.2, clustered variance 5/4 * 2.8 / 20^2 = 0.00875
    # against the binomial 0.8 * 0.2 / 20 = 0.008: 20 / 1.09375 effective trials.
    groups = np.repeat(np.arange(5), 4)
    correct = np.array([1, 1, 1, 1, 1, 1, 1, 0, 1, 1, 1, 1, 1, 1, 0, 0, 1, 1, 1, 0], dtype=float)
    np.testing.assert_allclose(
        _cluster_interval(correct, groups), wilson_by_hand(0.8, 20 / 1.09375)
    )
    # Hits 4, 4, 4, 0, 4: the clustered variance is five times the binomial, more than the largest
    # design effect, the group size 4: five effective trials, one per vehicle.
    correct = np.array([1.0] * 12 + [0.0] * 4 + [1.0] * 4)
    np.testing.assert_allclose(_cluster_interval(correct, groups), wilson_by_hand(0.8, 5))
    # All right: no variance to go by, so one trial per vehicle again; the interval is not [1, 1].
    np.testing.assert_allclose(_cluster_interval(np.ones(20), groups), wilson_by_hand(1.0, 5))


def boosted_between(features, groups, is_real, **options):
    """The boosted test of the rows where ``is_real`` against the others."""
    return boosted_two_sample_test(
        features[is_real],
        features[~is_real],
        real_groups=groups[is_real],
        generated_groups=groups[~is_real],
        **options,
    )


def test_no_vehicle_is_in_both_training_and_test_folds():
    # Each vehicle has a fingerprint (its own feature value), and a vehicle's segments are all
    # real or all generated, with no other difference: only a classifier tested on vehicles it was
    # trained on can tell them apart. Seeds 9 (data) and 10 (test).
    rng = np.random.default_rng(9)
    vehicles = np.repeat([f"v{n}" for n in range(60)], 5)
    fingerprint = np.repeat(rng.normal(size=60), 5)[:, None] + 0.01 * rng.normal(size=(300, 1))
    real = np.repeat(np.arange(60) % 2 == 0, 5)
    folds = grouped_folds(vehicles, 5)
    for fold in range(5):
        assert not set(vehicles[folds == fold]) & set(vehicles[folds != fold])
    # permutations=0: the accuracy alone.
    grouped = boosted_between(fingerprint, vehicles, real, seed=10, permutations=0)
    # The control: every segment its own group, so a vehicle's segments land in several folds.
    leaking = boosted_between(fingerprint, np.arange(300), real, seed=10, permutations=0)
    # 60 vehicles: chance accuracy has sd about 0.065 at the vehicle level; 0.7 is 3 sd above.
    assert grouped.accuracy < 0.7 and grouped.groups == 60
    assert leaking.accuracy > 0.85


def trafficgen_segments(seed: int, mechanisms: dict | None, steps: int = 50):
    """Features of 5 s segments of every trafficgen follower, and their vehicle ids."""
    recording = trafficgen.simulate(
        seed, mechanisms, platoons=2, followers=4, duration_s=40.0, cut_ins=0
    )
    speed, gap, lead, vehicles = [], [], [], []
    for row in np.flatnonzero(recording.follower):
        leader = recording.leader[row, 0]
        assert np.all(recording.leader[row] == leader)  # no cut-ins: one leader throughout
        for start in range(0, recording.v.shape[1] - steps, steps):
            window = slice(start, start + steps + 1)
            speed.append(recording.v[row, window])
            gap.append(recording.headway[row, window] - recording.length[leader])
            lead.append(recording.v[leader, window])
            vehicles.append(recording.vehicle_id[row])
    features = trajectory_features(np.array(speed), np.array(gap), np.array(lead), recording.dt)
    return features, np.array(vehicles)


def test_boosted_classifier_detects_a_hidden_effect():
    # trafficgen's seed 3 traffic with and without Ornstein-Uhlenbeck pedal noise (the same heads
    # and drivers: adding a mechanism leaves the other streams alone), 8 followers, 64 segments
    # each; test seed 4. 39 permutations: the smallest p-value is 1/40.
    plain, vehicles = trafficgen_segments(3, None)
    noisy, same_vehicles = trafficgen_segments(
        3, {"pedal_noise": trafficgen.MECHANISMS["pedal_noise"].sizes["medium"]}
    )
    result = boosted_two_sample_test(
        plain,
        noisy,
        real_groups=vehicles,
        generated_groups=same_vehicles,
        seed=4,
        folds=4,
        permutations=39,
    )
    assert result.accuracy > 0.8 and result.p_value < 0.05


@pytest.mark.realdata
def test_boosted_classifier_is_at_chance_on_two_halves_of_real_data(data_dir):
    # The negative control: NGSIM I-80's 5 s held-out windows of single followers, vehicles split
    # at random (seed 0) into two halves, test seed 0. About 230 segments of about 170 vehicles in
    # 4 folds: chance accuracy has sd about 0.04; the tolerance, 0.12, is 3 sd.
    traj = registry.load("ngsim_i80_chains", data_dir=data_dir)
    scenarios = platoon_scenarios(traj, vehicles_per_scenario=1, horizon_s=5.0).scenarios
    features = trajectory_features(
        np.array([s.v[1] for s in scenarios]),
        np.array([s.gap[0] for s in scenarios]),
        np.array([s.v[0] for s in scenarios]),
        traj.dt,
    )
    vehicles = np.array([s.simulated_ids[0] for s in scenarios])
    distinct = np.unique(vehicles)
    first_half = np.isin(vehicles, np.random.default_rng(0).permutation(distinct)[::2])
    result = boosted_between(features, vehicles, first_half, seed=0, folds=4, permutations=19)
    assert abs(result.accuracy - 0.5) < 0.12 and result.p_value > 0.05
    assert result.groups == len(distinct)


@pytest.mark.extended
def test_the_boosted_tests_result_does_not_depend_on_how_many_cores_share_it(monkeypatch):
    # The fits are split over the cores in slices of labellings: one core and two worker
    # processes give the same hits, so the same accuracy and p-value. Seeds 12 (data) and 13
    # (test).
    monkeypatch.setattr(two_sample, "PARALLEL_FITS", 0)
    rng = np.random.default_rng(12)
    vehicles = np.repeat(np.arange(20), 4)
    features = rng.normal(size=(80, 3)) + 2.0 * (vehicles % 2 == 0)[:, None]
    real = vehicles % 2 == 0
    results = []
    for cores in (1, 2):
        monkeypatch.setattr("os.cpu_count", lambda cores=cores: cores)
        results.append(boosted_between(features, vehicles, real, seed=13, permutations=7))
    assert results[0] == results[1]
    assert results[0].permutations == 7 and results[0].accuracy > 0.6
