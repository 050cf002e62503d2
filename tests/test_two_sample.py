"""The classifier two-sample test: chance on identical distributions, power on different ones."""

import numpy as np

from bayesdrive.simulation.two_sample import classifier_two_sample_test, segment_features


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
